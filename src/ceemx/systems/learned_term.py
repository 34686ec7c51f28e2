"""The learned term of a hybrid model: a network on normalised states and inputs.

:class:`LearnedTerm` is s_out ⊙ net([(x − μ_x)/s_x, (u − μ_u)/s_u]), optionally written into
chosen entries of the model's vector only; :func:`learned_term` builds one around an
``eqx.nn.MLP`` whose output layer is zero (so a hybrid starts as its physics model exactly);
:func:`weight_decay` is the Gaussian prior on the terms' weights. The hybrids that hold them:
:mod:`ceemx.systems.hybrid`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import cast

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray, Scalar

from ceemx.infra.memory import check_fits
from ceemx.infra.options import check_bool, check_int, check_positive
from ceemx.lib.tree import as_jax
from ceemx.models.constraints import param
from ceemx.models.system import AbstractSystem
from ceemx.systems.neural import init_mlp

__all__ = ["LearnedTerm", "check_mlp", "learned_term", "weight_decay"]


class LearnedTerm(eqx.Module):
    """s_out ⊙ net([(x − μ_x)/s_x, (u − μ_u)/s_u]): a network on normalised states and inputs.

    Attributes:
        net: any Equinox module mapping the normalised (n + p) vector (only the state inputs
            when ``use_input`` is False) to an out-dimensional vector.
        x_mean, x_scale: (n,) state normalisation (fixed).
        u_mean, u_scale: (p,) input normalisation (fixed; empty when there is no input).
        out_scale: (out,) output scale s_out (fixed).
        prior_std: the weight-decay prior's standard deviation of each weight
            (:func:`weight_decay`; static).
        use_input: whether the network sees the input (static).
        targets: the entries of the model's vector the term adds to (static; ``None``: all, the
            network's output is then the whole vector). Restricting a dynamics term to the
            equations that miss physics (a friction force enters the velocity equation only)
            keeps the hidden states' meaning: a term on every equation can trade a change of
            the hidden coordinates for the missing physics.
        size: the length of the model's vector (static; the output length when ``targets`` is
            ``None``).
    """

    net: eqx.Module
    x_mean: Float[Array, " n"] = param(fixed=True)
    x_scale: Float[Array, " n"] = param(fixed=True)
    u_mean: Float[Array, " p"] = param(fixed=True)
    u_scale: Float[Array, " p"] = param(fixed=True)
    out_scale: Float[Array, " out"] = param(fixed=True)
    prior_std: float = eqx.field(static=True, default=1.0)
    use_input: bool = eqx.field(static=True, default=True)
    targets: tuple[int, ...] | None = eqx.field(static=True, default=None)
    size: int | None = eqx.field(static=True, default=None)

    def __call__(self, x: Float[Array, " n"], u: Float[Array, " p"]) -> Float[Array, " size"]:
        """The term's value at (x, u): a vector of the model's length."""
        z = (x - self.x_mean) / self.x_scale
        if self.use_input and self.u_mean.shape[0]:
            z = jnp.concatenate([z, (u - self.u_mean) / self.u_scale])
        out = self.out_scale * self.net(z)  # type: ignore[operator]
        if self.targets is None:
            return out
        assert self.size is not None
        return jnp.zeros((self.size,), out.dtype).at[jnp.asarray(self.targets)].set(out)


def learned_term(
    key: PRNGKeyArray,
    *,
    x_mean: ArrayLike,
    x_scale: ArrayLike,
    out_scale: ArrayLike,
    u_mean: ArrayLike | None = None,
    u_scale: ArrayLike | None = None,
    width: int = 16,
    depth: int = 2,
    activation: Callable = jnp.tanh,
    prior_std: float = 1.0,
    use_input: bool = True,
    targets: tuple[int, ...] | None = None,
    size: int | None = None,
    net: eqx.Module | None = None,
    dtype=None,
) -> LearnedTerm:
    """A :class:`LearnedTerm` around an ``eqx.nn.MLP`` whose output layer is zero.

    Args:
        key: PRNG key of the hidden layers' initial weights.
        x_mean: (n,) state mean μ_x.
        x_scale: (n,) state scale s_x (positive).
        out_scale: (out,) scale of the output (positive); its length is the network's output
            dimension (``len(targets)`` when given).
        u_mean: (p,) input mean μ_u (``None``: no input).
        u_scale: (p,) input scale s_u (positive; ``None``: no input).
        width: the MLP's hidden width.
        depth: the MLP's number of hidden layers.
        activation: the MLP's hidden activation.
        prior_std: standard deviation of the weight-decay prior (:func:`weight_decay`).
        use_input: whether the network sees the input.
        targets: the entries of the model's ``size``-vector the output is added to (``None``:
            all; :class:`LearnedTerm`).
        size: the model vector's length (required with ``targets``).
        net: any Equinox module instead of the MLP (used as given: zero its output yourself to
            start at the physics model).
        dtype: floating dtype (default: ``x_mean``'s, else JAX's default float).

    Raises:
        ValueError: non-positive or non-finite scales, mismatched lengths, bad width/depth.
    """
    arrays, dtype = _normalisation(x_mean, x_scale, u_mean, u_scale, out_scale, dtype)
    n, p, out = arrays["x_mean"].shape[0], arrays["u_mean"].shape[0], arrays["out_scale"].shape[0]
    if targets is not None:
        targets = _check_targets(targets, size, out)
    check_positive("prior_std", prior_std)
    check_bool("use_input", use_input)
    if net is None:
        n_in = n + (p if use_input else 0)
        check_mlp(width, depth, n_in, out, np.dtype(dtype).itemsize)
        net = init_mlp(key, n_in, out, width, depth, activation, dtype, 0.0)  # output zero
    assert net is not None
    return LearnedTerm(
        net,
        prior_std=float(prior_std),
        use_input=use_input,
        targets=targets,
        size=size,
        **{k: as_jax(a) for k, a in arrays.items()},
    )


def check_mlp(width, depth, n_in: int, out: int, itemsize: int) -> None:
    """Raise, before any allocation, for a bad ``width``/``depth`` or an MLP too big to build.

    The estimate is twice the weights (the initialisation's random draws and the scaled weights
    live at once); a network past the machine's memory otherwise fails inside XLA — past about
    10⁹ weights per layer with an abort of the whole process, not an exception.
    """
    width = cast(int, check_int("width", width, 1))
    depth = cast(int, check_int("depth", depth, 0))
    if depth == 0:
        weights = (n_in + 1) * out
    else:
        weights = (n_in + 1) * width + (depth - 1) * (width + 1) * width + (width + 1) * out
    check_fits(
        f"the {weights:.3g} weights of an MLP of width {width} and depth {depth}",
        2 * weights * itemsize,
        "pass a smaller `width` or `depth`.",
    )


def _normalisation(x_mean, x_scale, u_mean, u_scale, out_scale, dtype):
    """The normalisation arrays, checked, and the term's dtype.

    The dtype defaults to ``x_mean``'s when floating, else JAX's default float. Host-side
    (NumPy) conversions and checks: op by op in JAX each compiled a small program.
    """
    x_mean = np.asarray(x_mean)
    x_dtype = jax.dtypes.canonicalize_dtype(x_mean.dtype)
    dtype = dtype or (x_dtype if jnp.issubdtype(x_dtype, jnp.floating) else None)
    dtype = dtype or jax.dtypes.canonicalize_dtype(float)
    stored = jax.dtypes.canonicalize_dtype(dtype)  # what jnp.asarray(·, dtype) would store
    arrays = {
        "x_mean": np.atleast_1d(np.asarray(x_mean, stored)),
        "x_scale": np.atleast_1d(np.asarray(x_scale, stored)),
        "u_mean": np.asarray(() if u_mean is None else u_mean, stored).reshape(-1),
        "u_scale": np.asarray(() if u_scale is None else u_scale, stored).reshape(-1),
        "out_scale": np.atleast_1d(np.asarray(out_scale, stored)),
    }
    n, p = arrays["x_mean"].shape[0], arrays["u_mean"].shape[0]
    for name, length in (("x_scale", n), ("u_scale", p)):
        if arrays[name].shape[0] != length:
            raise ValueError(
                f"`{name}` must have the length of its mean ({length}); got "
                f"{arrays[name].shape[0]}."
            )
    for name in ("x_scale", "u_scale", "out_scale"):
        a = arrays[name]
        if not bool(np.all(np.isfinite(a) & (a > 0))):
            raise ValueError(f"`{name}` must be positive and finite; got {a}.")
    for name in ("x_mean", "u_mean"):
        if not bool(np.all(np.isfinite(arrays[name]))):
            raise ValueError(f"`{name}` must be finite; got {arrays[name]}.")
    return arrays, dtype


def _check_targets(targets, size: int | None, out: int) -> tuple[int, ...]:
    """``targets`` as ``out`` distinct indices in [0, ``size``); or raise."""
    targets = tuple(int(i) for i in targets)
    if size is None or len(targets) != out or len(set(targets)) != out:
        raise ValueError(
            f"`targets` must be {out} distinct indices (one per output) with `size` given; "
            f"got targets={targets}, size={size}."
        )
    if not all(0 <= i < size for i in targets):
        raise ValueError(f"`targets` must lie in [0, size = {size}); got {targets}.")
    return targets


def weight_decay(system: AbstractSystem) -> Scalar:
    """The weight-decay log-prior −½ Σ w²/σ² over every :class:`LearnedTerm` of ``system``.

    σ is each term's ``prior_std``.

    A Gaussian prior on the networks' weights and biases (weight decay), for
    ``ceemx.fit(model, data, log_prior=weight_decay)``; 0 for a system without learned terms.
    Constants are dropped (they do not move the fit).
    """
    terms = [
        leaf
        for leaf in jtu.tree_leaves(system, is_leaf=lambda v: isinstance(v, LearnedTerm))
        if isinstance(leaf, LearnedTerm)
    ]
    total = jnp.zeros(())
    for term in terms:
        weights = jtu.tree_leaves(eqx.filter(term.net, eqx.is_inexact_array))
        ss = sum((jnp.sum(jnp.square(w)) for w in weights), jnp.zeros(()))
        total = total - 0.5 * ss / term.prior_std**2
    return total
