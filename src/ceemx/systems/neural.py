"""Linear dynamics read out by a linear map plus a neural network (paper Eq. 17: the NL model)."""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray, Real

from ceemx.lib.typing import State
from ceemx.models.noise import AbstractNoise, as_noise
from ceemx.models.system import AbstractSystem, GaussianPrior

__all__ = ["NeuralObservationSystem"]


class NeuralObservationSystem(AbstractSystem):
    r"""x_{t+1} = A x_t + B u_t + w_t,   y_t = C x_t + D u_t + NN(x_t, u_t) + v_t  (paper Eq. 17).

    The paper's NL model of the helicopter's residual accelerations: a linear latent system (a
    Koopman-style lift, §4.2.3) read out through a linear map plus a multilayer perceptron of the
    state and the input. The network's input is the concatenation (x, u); its last layer is
    scaled by ``gain`` at initialisation so the model starts close to the linear one it is
    hot-started from (the authors' ``gain = 0.1``).

    Attributes:
        A: (n, n); B: (n, p); C: (m, n); D: (m, p).
        net: the MLP (n + p → m).
        process_noise, obs_noise: p_w, p_v (paper: σ_w = σ_v = 1).
        initial_prior: prior on x₁ or ``None``.
    """

    A: Float[Array, "n n"]
    B: Float[Array, "n p"]
    C: Float[Array, "m n"]
    D: Float[Array, "m p"]
    net: eqx.nn.MLP

    def __init__(
        self,
        A: ArrayLike,
        B: ArrayLike,
        C: ArrayLike,
        D: ArrayLike,
        *,
        key: PRNGKeyArray,
        width: int = 32,
        depth: int = 2,
        activation: Callable = jnp.tanh,
        gain: float = 0.1,
        process_noise: AbstractNoise | ArrayLike = 1.0,
        obs_noise: AbstractNoise | ArrayLike = 1.0,
        initial_prior: GaussianPrior | None = None,
    ):
        """Build the model around given linear matrices (e.g. an N4SID fit).

        Args:
            A: (n, n) transition; its floating dtype is the model's (everything is cast to it).
            B: (n, p) input matrix.
            C: (m, n) observation matrix.
            D: (m, p) feedthrough.
            key: PRNG key of the network's initial weights.
            width: hidden layer width (authors: 32).
            depth: number of hidden layers (authors: 2).
            activation: hidden activation (authors: tanh).
            gain: factor on the last layer's initial weights and bias (authors: 0.1).
            process_noise: noise model or scale of w (default 1, the paper's).
            obs_noise: noise model or scale of v (default 1, the paper's).
            initial_prior: optional prior on x₁.

        Raises:
            ValueError: when the matrices' shapes disagree, naming the matrix.
        """
        A = jnp.asarray(A)
        dtype = A.dtype if jnp.issubdtype(A.dtype, jnp.floating) else jnp.zeros(()).dtype
        self.A = A.astype(dtype)
        self.B = jnp.asarray(B, dtype)
        self.C = jnp.asarray(C, dtype)
        self.D = jnp.asarray(D, dtype)
        n = self.A.shape[0]
        if self.A.ndim != 2 or self.A.shape != (n, n):
            raise ValueError(f"`A` must be square (n, n); got shape {self.A.shape}.")
        if self.B.ndim != 2 or self.B.shape[0] != n:
            raise ValueError(f"`B` must have shape ({n}, p); got {self.B.shape}.")
        p = self.B.shape[1]
        if self.C.ndim != 2 or self.C.shape[1] != n:
            raise ValueError(f"`C` must have shape (m, {n}); got {self.C.shape}.")
        m = self.C.shape[0]
        if self.D.shape != (m, p):
            raise ValueError(f"`D` must have shape ({m}, {p}); got {self.D.shape}.")
        self.net = init_mlp(key, n + p, m, width, depth, activation, dtype, gain)

        def noise(value, dim):
            if isinstance(value, AbstractNoise):
                return value
            return as_noise(jnp.asarray(value, dtype), dim)

        self.process_noise = noise(process_noise, n)
        self.obs_noise = noise(obs_noise, m)
        self.initial_prior = initial_prior

    @property
    def state_dim(self) -> int:
        """N."""
        return self.A.shape[0]

    @property
    def obs_dim(self) -> int:
        """M."""
        return self.C.shape[0]

    @property
    def input_dim(self) -> int:
        """P."""
        return self.B.shape[1]

    def dynamics(self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]) -> State:
        """A x + B u."""
        return self.A @ x + self.B @ u

    def observe(
        self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]
    ) -> Float[Array, " m"]:
        """C x + D u + NN(x, u)."""
        return self.C @ x + self.D @ u + self.net(jnp.concatenate([x, u]))


def init_mlp(key, n_in: int, out: int, width: int, depth: int, activation, dtype, gain: float):
    """``eqx.nn.MLP(n_in, out, width, depth)`` with its last layer's weight and bias × ``gain``.

    Built by one compiled program per configuration: op by op, Equinox's initialisation compiled
    two random draws per layer and the scaling more at every new shape (≈ 20–150 ms each). The
    gain is an argument of that program, not part of the configuration: the zero-initialised
    learned terms (gain 0) and the Eq.-17 networks (gain 0.1) share it.
    """
    gain_array = np.asarray(float(gain), jax.dtypes.canonicalize_dtype(dtype or float))
    return _init_mlp(key, n_in, out, width, depth, activation, dtype, gain_array)


@eqx.filter_jit
def _init_mlp(key, n_in, out, width, depth, activation, dtype, gain):
    net = eqx.nn.MLP(n_in, out, width, depth, activation=activation, key=key, dtype=dtype)
    last = net.layers[-1]
    scaled = (last.weight * gain, None if last.bias is None else last.bias * gain)
    return eqx.tree_at(
        lambda mlp: (mlp.layers[-1].weight, mlp.layers[-1].bias),
        net,
        scaled,
        is_leaf=lambda x: x is None,
    )
