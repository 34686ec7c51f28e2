"""The paper's LSTM baseline (§4.2.2): a stacked LSTM of the inputs with a linear read-out.

h⁰_t = u_t, (hˡ_t, cˡ_t) = LSTMCellˡ(hˡ⁻¹_t, (hˡ_{t−1}, cˡ_{t−1})) for l = 1, …, L from zero
states, ŷ_t = W h^L_t + b. The authors' network (``experiments/heli/train_lstm.py``): L = 2 layers
of 32 units and a linear head, on the inputs only; in the paper it models the naive model's
residual ỹ = y − NN(u) (compose with :class:`ceemx.evaluation.prediction.ResidualPredictor`). It
never reads y, and ŷ_t depends on u_1, …, u_t only.
"""

from __future__ import annotations

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

__all__ = ["LSTMRegressor"]


class LSTMRegressor(AbstractPredictor):
    """ŷ_t = W h_t + b with h_t the last layer of a stacked LSTM run over u_1, …, u_t.

    Attributes:
        cells: the LSTM layers, first to last (Equinox ``LSTMCell``s).
        head: the linear read-out (hidden, → m).
    """

    cells: tuple[eqx.nn.LSTMCell, ...]
    head: eqx.nn.Linear

    def __init__(
        self,
        input_dim: int,
        output_dim: int,
        *,
        hidden: int = 32,
        layers: int = 2,
        dtype=None,
        key: PRNGKeyArray,
    ):
        """A randomly initialised network.

        Every weight and bias U(−1/√hidden, 1/√hidden): PyTorch's initialisation of the LSTM and
        of the head (whose fan-in is ``hidden``), which the authors used.

        Args:
            input_dim: p, the input dimension.
            output_dim: m, the output dimension.
            hidden: units per layer (authors: 32).
            layers: stacked LSTM layers (authors: 2).
            dtype: parameter dtype (default: JAX's default float).
            key: PRNG key of the initialisation.
        """
        if int(input_dim) < 1 or int(output_dim) < 1 or int(hidden) < 1 or int(layers) < 1:
            raise ValueError(
                "`input_dim`, `output_dim`, `hidden` and `layers` must be >= 1; got "
                f"{input_dim}, {output_dim}, {hidden} and {layers}."
            )
        h, sizes = int(hidden), [int(input_dim)] + [int(hidden)] * int(layers)
        shapes = eqx.filter_eval_shape(
            lambda k: (
                tuple(
                    eqx.nn.LSTMCell(sizes[i], sizes[i + 1], dtype=dtype, key=k)
                    for i in range(int(layers))
                ),
                eqx.nn.Linear(h, int(output_dim), dtype=dtype, key=k),
            ),
            key,
        )
        self.cells, self.head = _uniform_init(shapes, key, 1.0 / np.sqrt(h))

    @property
    def input_dim(self) -> int:
        """p, the input dimension."""
        return self.cells[0].input_size

    @property
    def output_dim(self) -> int:
        """m, the output dimension."""
        return self.head.out_features  # pyright: ignore[reportReturnType]

    def __call__(self, u: Float[Array, "T p"]) -> Float[Array, "T m"]:
        """(T, m) predictions of one trajectory: a ``lax.scan`` over time from zero states."""
        dtype = self.head.weight.dtype
        states = tuple(
            (jnp.zeros(c.hidden_size, dtype), jnp.zeros(c.hidden_size, dtype)) for c in self.cells
        )

        def step(carry, u_t):
            x = u_t
            new = []
            for cell, state in zip(self.cells, carry, strict=True):
                h, c = cell(x, state)
                new.append((h, c))
                x = h
            return tuple(new), x

        _, hs = jax.lax.scan(step, states, u)
        return jax.vmap(self.head)(hs)

    def predict(self, data: Trajectories) -> Observations:
        """(B, T, m) predictions from the inputs (never reads ``data.y``); vmapped over B."""
        return _predict_lstm(self, data.u)


@jit
def _predict_lstm(model: LSTMRegressor, u: Float[Array, "B T p"]) -> Float[Array, "B T m"]:
    return jax.vmap(model)(u)


def _uniform_init(shapes, key: PRNGKeyArray, bound: float):
    """Every array of ``shapes`` (a pytree of shapes) drawn U(−bound, bound) from one draw.

    One random operation for the whole network, sliced on the host: building the network then
    dispatches (and compiles) a single operation, not one per weight.
    """
    leaves, treedef = jax.tree_util.tree_flatten(shapes)
    sizes = [int(np.prod(leaf.shape)) for leaf in leaves]
    dtype = leaves[0].dtype
    draw = jax.random.uniform(key, (sum(sizes),), dtype, -bound, bound)
    xp = jnp if isinstance(draw, Tracer) else np  # under jit/vmap: traced
    draw = xp.asarray(draw)
    out, offset = [], 0
    for leaf, size in zip(leaves, sizes, strict=True):
        out.append(jnp.asarray(draw[offset : offset + size].reshape(leaf.shape), dtype))
        offset += size
    return jax.tree_util.tree_unflatten(treedef, out)
