r"""Lagged-input regressors: the paper's naive (H = 1) and H25 (H = 25) models (§4.2.2).

.. math::

    \hat y_t = \mathrm{NN}_\theta\big(\operatorname{vec}(u_{t-H+1}, \dots, u_t)\big)

a multilayer perceptron of the flattened window of the last H inputs. The authors' network
(``ceem/baseline_utils.py``) has 8 hidden layers of 32 tanh units, a linear output layer, weights
initialised with unit-norm rows (each unit's incoming weight vector drawn N(0, I) and normalised)
and zero biases; these are the defaults here.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, Float, PRNGKeyArray

from ceemx.data.trajectories import Trajectories
from ceemx.evaluation.prediction import AbstractPredictor
from ceemx.infra.compilation import jit
from ceemx.lib.typing import Observations

__all__ = ["LagRegressor", "lag_windows"]


def _unit_row_layers(mlp: eqx.nn.MLP, key: PRNGKeyArray) -> eqx.nn.MLP:
    """The authors' initialisation of every layer: rows of W ~ N(0, I) scaled to norm 1, b = 0.

    ``mlp`` may hold only shapes (``eqx.filter_eval_shape``): the weights come from one normal
    draw, sliced and normalised on the host, so building the network outside ``jit`` dispatches
    (and compiles) a single random operation however deep it is.
    """
    sizes = [int(np.prod(lin.weight.shape)) for lin in mlp.layers]
    dtype = mlp.layers[0].weight.dtype
    draw = jax.random.normal(key, (sum(sizes),), dtype)
    xp = jnp if isinstance(draw, Tracer) else np  # under jit/vmap: traced
    draw = xp.asarray(draw)
    layers, offset = [], 0
    for lin, size in zip(mlp.layers, sizes, strict=True):
        w = draw[offset : offset + size].reshape(lin.weight.shape)
        offset += size
        w = w / xp.linalg.norm(w, axis=1, keepdims=True)
        b = None if lin.bias is None else xp.zeros(lin.bias.shape, dtype)
        new = (jnp.asarray(w, dtype), None if b is None else jnp.asarray(b, dtype))
        layers.append(eqx.tree_at(lambda x: (x.weight, x.bias), lin, new, is_leaf=_is_none))
    return eqx.tree_at(lambda m: m.layers, mlp, tuple(layers))


def _is_none(x) -> bool:
    return x is None


def lag_windows(u: Float[Array, "T p"], lags: int) -> Float[Array, "T H p"]:
    """The window (u_{t−H+1}, …, u_t) of every step t of one trajectory, edge-padded.

    For t < H − 1 the missing inputs before the first step are copies of u₀ (edge padding), so
    every step gets a prediction; scores of H-lag models should start at t ≥ H − 1 (the paper's
    evaluation scores t ≥ 25).

    Args:
        u: (T, p) inputs of one trajectory.
        lags: H ≥ 1.

    Returns:
        (T, H, p) windows, oldest input first: ``windows[t, H − 1] = u[t]``.
    """
    T = u.shape[0]
    padded = jnp.concatenate([jnp.broadcast_to(u[:1], (lags - 1, u.shape[1])), u], axis=0)
    index = jnp.arange(T)[:, None] + jnp.arange(lags)[None, :]
    return padded[index]


class LagRegressor(AbstractPredictor):
    """ŷ_t = MLP(vec(u_{t−H+1}, …, u_t)): a regressor of the last H inputs (never of y).

    H = 1 is the paper's *naive* model y_t = NN(u_t); H = 25 its *H25* model (after Punjani &
    Abbeel, 2015). Steps t < H − 1 see edge-padded windows (u₀ repeated, :func:`lag_windows`).

    Attributes:
        mlp: the network, input size H·p, output size m.
        lags: H, the number of inputs in a window.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> from ceemx import Trajectories
        >>> model = LagRegressor(2, 1, lags=3, width=8, depth=2, key=jax.random.PRNGKey(0))
        >>> data = Trajectories(jnp.zeros((4, 10, 1)), jnp.ones((4, 10, 2)))
        >>> model.predict(data).shape
        (4, 10, 1)
    """

    mlp: eqx.nn.MLP
    lags: int = eqx.field(static=True)

    def __init__(
        self,
        input_dim: int,
        output_dim: int,
        lags: int = 1,
        *,
        width: int = 32,
        depth: int = 8,
        activation: Callable = jnp.tanh,
        dtype=None,
        key: PRNGKeyArray,
    ):
        """Build the network.

        Args:
            input_dim: p, the input dimension.
            output_dim: m, the output dimension.
            lags: H ≥ 1 (1: naive model; 25: H25 model).
            width: units per hidden layer (authors: 32).
            depth: number of hidden layers (authors: 8).
            activation: hidden activation (authors: tanh); the output layer is linear.
            dtype: parameter dtype (``None``: JAX's default floating dtype).
            key: PRNG key of the initialisation (unit-norm rows, zero biases, as the authors).
        """
        if lags < 1:
            raise ValueError(f"`lags` must be >= 1; got {lags}.")
        shapes = eqx.filter_eval_shape(
            eqx.nn.MLP, lags * input_dim, output_dim, width, depth, activation, dtype=dtype, key=key
        )
        self.mlp = _unit_row_layers(shapes, key)
        self.lags = int(lags)

    @property
    def input_dim(self) -> int:
        """p, the input dimension."""
        return int(self.mlp.in_size) // self.lags  # type: ignore[arg-type]

    @property
    def output_dim(self) -> int:
        """m, the output dimension."""
        return int(self.mlp.out_size)  # type: ignore[arg-type]

    def __call__(self, window: Float[Array, "H p"]) -> Float[Array, " m"]:
        """ŷ of one window (u_{t−H+1}, …, u_t), oldest first."""
        return self.mlp(window.reshape(-1))

    def predict_inputs(self, u: Float[Array, "T p"]) -> Float[Array, "T m"]:
        """(T, m) predictions of one trajectory from its inputs alone."""
        return jax.vmap(self)(lag_windows(u, self.lags))

    def predict(self, data: Trajectories) -> Observations:
        """(B, T, m) predictions ŷ_t from u_{t−H+1..t}; ``data.y`` is never read.

        For H > 1 trajectories are processed 32 at a time (``lax.map``), so the (T, H, p)
        windows of only 32 trajectories are held at a time.
        """
        return _predict_lag(self, data.u)


@jit
def _predict_lag(model: LagRegressor, u: Float[Array, "B T p"]) -> Float[Array, "B T m"]:
    if model.lags == 1:
        return jax.vmap(model.predict_inputs)(u)
    return jax.lax.map(model.predict_inputs, u, batch_size=32)
