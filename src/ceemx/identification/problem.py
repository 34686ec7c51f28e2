"""The identification problem shared by every fit solver: data, the trainable split of θ, prior.

A :class:`FitProblem` knows how to rebuild the system from the flat vector θ of its trainable
leaves and how to evaluate the CE-EM objective −J(x, θ) (paper Eq. 9) and the log-prior. It holds no
iterate: solvers keep (θ, x) in their state.

θ is unconstrained. A leaf whose field declares a constraint (:func:`ceemx.param`) enters θ as
z = inverse(x) and the system is rebuilt with x = forward(z) (:mod:`ceemx.models.constraints`), so
every solver, learner and checkpoint — they all go through :meth:`FitProblem.create` and
:meth:`FitProblem.build` — works in unconstrained coordinates, while systems (and so ``log_prior``,
which is evaluated on the built system) are in natural units. The trust region ρ_θ‖θ − θᵏ‖² of the
learners and the joint method, and the history's ``dtheta_norm``, measure θ, i.e. the
unconstrained coordinates; ``log_prior`` is a density of the natural values maximised over θ with
no change-of-variables term (a penalty in natural units, not a density of θ).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax.core import Tracer
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float, PyTree

from ceemx.data.trajectories import Trajectories
from ceemx.inference.objective import neg_log_joint_single, nll_offset
from ceemx.infra.compilation import jit
from ceemx.infra.policy import Runs, program
from ceemx.lib.dense import symmetrize
from ceemx.lib.tree import as_jax, is_weak
from ceemx.lib.typing import PerTrajectory, Scalar, States, Theta
from ceemx.models.constraint_checks import check_constraints, check_room
from ceemx.models.constraints import (
    AbstractConstraint,
    Positive,
    Unconstrained,
)
from ceemx.models.noise import AbstractNoise
from ceemx.models.parameter_meta import Overrides, leaf_constraints_with
from ceemx.models.system import AbstractSystem, GaussianPrior, float_dtype

__all__ = [
    "FitProblem",
    "Trainable",
    "per_trajectory_nll",
    "per_trajectory_offset",
    "split_system",
    "trainable_mask",
]

Trainable = Callable[[AbstractSystem], Any] | PyTree | None
"""Which leaves of a system learn: see :func:`trainable_mask`."""


def trainable_mask(
    system: AbstractSystem,
    trainable: Trainable = None,
    *,
    noise: bool = False,
    overrides: Overrides = (),
) -> PyTree:
    """A boolean pytree over ``system`` marking the leaves that learn.

    Args:
        system: the model.
        trainable: ``None`` — every floating-point array of the model except its noise models and
            initial-state prior; a callable ``where(system)`` returning the leaves or sub-trees to
            learn (as in ``eqx.tree_at``), e.g. ``lambda s: (s.sigma, s.rho, s.beta)``; or a boolean
            pytree with the structure of ``system`` (an Equinox filter spec).

        noise: also mark the floating-point leaves of ``process_noise`` and ``obs_noise`` (for
            :class:`ceemx.LaplaceEM`, which learns noise covariances:
            ``fit(model, data, solver=ceemx.LaplaceEM(), trainable=trainable_mask(model,
            noise=True))``).
        overrides: per-fit constraints by leaf name
            (:func:`~ceemx.models.parameter_meta.leaf_constraints_with`); a
            :class:`~ceemx.models.constraints.Fixed` one holds its leaf.

    Returns:
        Booleans with the structure of ``system``. Leaves of fields declared
        ``ceemx.param(fixed=True)`` are always ``False``, whatever ``trainable`` selects.
    """
    mask = _drop_fixed(system, _selected(system, trainable), overrides)
    if noise:
        on = tuple(
            jtu.tree_map(eqx.is_inexact_array, getattr(system, f))
            for f in ("process_noise", "obs_noise")
        )
        mask = eqx.tree_at(lambda s: (s.process_noise, s.obs_noise), mask, replace=on)
    return mask


def _selected(system: AbstractSystem, trainable: Trainable) -> PyTree:
    if trainable is None:
        # Noise models and priors never learn by default, the system's own or those of a
        # sub-model (a hybrid's physics model keeps its own, unused).
        def learns(node):
            if isinstance(node, AbstractNoise | GaussianPrior):
                return jtu.tree_map(lambda _: False, node)
            return eqx.is_inexact_array(node)

        return jtu.tree_map(
            learns, system, is_leaf=lambda v: isinstance(v, AbstractNoise | GaussianPrior)
        )
    if callable(trainable):
        mask = jtu.tree_map(lambda _: False, system)

        def where(s) -> tuple[Any, ...]:
            picked = trainable(s)
            return picked if isinstance(picked, tuple) else (picked,)

        replace = tuple(jtu.tree_map(eqx.is_inexact_array, c) for c in where(system))
        return eqx.tree_at(where, mask, replace=replace)
    return trainable


def _drop_fixed(system: AbstractSystem, mask: PyTree, overrides: Overrides = ()) -> PyTree:
    """``mask`` (a filter spec, possibly a prefix of ``system``) per leaf, with fixed leaves off."""
    leaves, treedef = jtu.tree_flatten(system)
    if not leaves:
        return mask

    def broadcast(spec, sub):
        return jtu.tree_map(lambda leaf: bool(spec(leaf) if callable(spec) else spec), sub)

    full = jtu.tree_map(broadcast, mask, system, is_leaf=lambda v: v is None)
    flags = treedef.flatten_up_to(full)
    constraints = leaf_constraints_with(system, overrides)
    kept = [bool(f) and c.trainable for f, c in zip(flags, constraints, strict=True)]
    return jtu.tree_unflatten(treedef, kept)


def split_system(
    system: AbstractSystem, trainable: Trainable = None
) -> tuple[Theta, PyTree, PyTree]:
    """(θ flat, params template, static part) for the trainable leaves of ``system``.

    Natural units: the leaves as the system holds them (:meth:`FitProblem.create` maps the
    constrained ones to unconstrained coordinates).
    """
    params, static = eqx.partition(system, trainable_mask(system, trainable))
    theta, _ = ravel_pytree(params)
    return theta, params, static


def _trainable_constraints(
    system: AbstractSystem, mask: PyTree, overrides: Overrides = ()
) -> list[AbstractConstraint]:
    """The constraint of each trainable leaf, in the order of the trainable sub-tree's leaves."""
    flags = jtu.tree_structure(system).flatten_up_to(mask)
    every = leaf_constraints_with(system, overrides)
    return [c for f, c in zip(flags, every, strict=True) if f]


def _trainable_names(system: AbstractSystem, mask: PyTree) -> list[str]:
    """``system.A``-style names of the trainable leaves, in the order of the trainable sub-tree."""
    flags = jtu.tree_structure(system).flatten_up_to(mask)
    pairs, _ = jtu.tree_flatten_with_path(system)
    return [f"system{jtu.keystr(path)}" for f, (path, _) in zip(flags, pairs, strict=True) if f]


def check_log_prior(log_prior: Callable[[AbstractSystem], Any] | None, system) -> None:
    """``log_prior`` must be callable and give a finite real scalar at the initial system.

    Evaluated once on the host (skipped inside ``jit``): a prior that is NaN or −inf where the fit
    starts would freeze θ (every step compares against NaN) while the fit reports success.

    Raises:
        TypeError, ValueError: naming ``log_prior`` and what it returned.
    """
    if log_prior is None:
        return
    if not callable(log_prior):
        raise TypeError(f"`log_prior` must be a callable system -> log p(θ); got {log_prior!r}.")
    if any(isinstance(a, Tracer) for a in jtu.tree_leaves(system)):
        return
    value = log_prior(system)
    if isinstance(value, Tracer):
        return
    try:
        a = np.asarray(value)
    except Exception:  # noqa: BLE001 — any object NumPy cannot read is the wrong kind
        a = np.asarray(None)
    if a.shape not in ((), (1,)) or not (
        np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)
    ):
        raise TypeError(
            f"`log_prior` must return a real scalar (log p(θ)); it returned {_describe(value)} "
            "at the initial system."
        )
    if not np.all(np.isfinite(a)):
        raise ValueError(
            f"`log_prior` is {a.item()!r} at the initial system: it must be finite where the fit "
            "starts (a NaN or infinite prior freezes θ). Check the prior's support and the "
            "initial parameters."
        )


def _describe(value: Any) -> str:
    shape = getattr(value, "shape", None)
    if shape is not None:
        return f"an array of shape {tuple(shape)} and dtype {getattr(value, 'dtype', '?')}"
    return repr(value)


def _strong(a):
    return jnp.asarray(a, dtype=jnp.result_type(a)) if eqx.is_array(a) else a


def _build(template, static, constraints, theta: Theta) -> AbstractSystem:
    """:meth:`FitProblem.build` of the problem's parts."""
    _, unravel = ravel_pytree(template)
    params = unravel(theta)
    if any(not isinstance(c, Unconstrained) for c in constraints):
        leaves, treedef = jtu.tree_flatten(params)
        natural = [c.forward(z) for c, z in zip(constraints, leaves, strict=True)]
        params = jtu.tree_unflatten(treedef, natural)
    return eqx.combine(params, static)


_build_compiled = jit(_build)


def _natural(template, constraints, theta: Theta) -> tuple[Array, Array]:
    """:meth:`FitProblem.natural` and :meth:`FitProblem.natural_jacobian` of θ, together."""
    _, unravel = ravel_pytree(template)
    leaves = jtu.tree_leaves(unravel(theta))
    constraints = constraints or (Unconstrained(),) * len(leaves)
    pairs = [
        jax.jvp(c.forward, (z,), (jnp.ones_like(z),))
        for c, z in zip(constraints, leaves, strict=True)
    ]
    natural, _ = ravel_pytree([p[0] for p in pairs])
    slope, _ = ravel_pytree([p[1] for p in pairs])
    return natural, slope


# On the host one one-shot program per problem structure (the identifiability analysis and the
# parameter covariance ask once per fit): op by op, a dozen small programs at each new shape.
_natural_compiled = program(_natural, runs=Runs.ONCE)


def _sign_definite(c: AbstractConstraint) -> bool:
    """Whether constraint ``c`` keeps its natural value on one side of zero."""
    lower, upper = getattr(c, "lower", None), getattr(c, "upper", None)
    return bool(
        isinstance(c, Positive)
        or (lower is not None and lower >= 0)
        or (upper is not None and upper <= 0)
    )


def _unconstrain(constraints, leaves) -> tuple[list, list, Theta]:
    """(z = inverse(x) per leaf, forward(z) per leaf, the flat θ of the z): θ of the leaves x."""
    unconstrained = [c.inverse(_strong(x)) for c, x in zip(constraints, leaves, strict=True)]
    back = [c.forward(z) for c, z in zip(constraints, unconstrained, strict=True)]
    theta, _ = ravel_pytree(unconstrained)
    return unconstrained, back, _strong(theta)


# On the host one program per problem structure: op by op, every constraint's inverse and the
# flattening compiled a handful of small programs at each new shape (≈ 20 ms each).
_unconstrain_compiled = program(_unconstrain, runs=Runs.ONCE)


def _unconstrained_leaves(constraints, leaves) -> tuple[list, list | None, Theta]:
    """:func:`_unconstrain` (``None`` for forward(z) when traced: :func:`check_room` skips)."""
    if leaves and not any(isinstance(x, Tracer) for x in leaves):
        return _unconstrain_compiled(tuple(constraints), list(leaves))
    unconstrained, _, theta = _unconstrain(constraints, leaves)  # traced: forward(z) unused
    return unconstrained, None, theta


def _cast_weak(a, dtype):
    """A weakly typed inexact array as a strong one of ``dtype`` (cast on the host if concrete)."""
    if not (eqx.is_inexact_array(a) and is_weak(a)):
        return a
    if isinstance(a, Tracer) or a.committed:
        return a.astype(dtype)
    return as_jax(np.asarray(a).astype(dtype))


class FitProblem(eqx.Module):
    """Data, the model split into trainable θ and the rest, and an optional log-prior.

    Attributes:
        template: the trainable sub-tree in unconstrained coordinates (its structure and shapes
            define the flat θ).
        static: the rest of the system (natural units).
        data: the observations.
        log_prior: ``None`` or a callable on the system returning log p(θ) (natural units).
        constraints: the constraint of each leaf of ``template``, in leaf order (θ's entries map
            to natural values through their ``forward``).
        overrides: the per-fit constraints by leaf name it was created with
            (:func:`~ceemx.models.parameter_meta.leaf_constraints_with`; kept for the problems
            derived from it).
    """

    template: Any
    static: Any
    data: Trajectories
    log_prior: Callable[[AbstractSystem], Any] | None = eqx.field(static=True, default=None)
    constraints: tuple[AbstractConstraint, ...] = eqx.field(static=True, default=())
    overrides: Overrides = eqx.field(static=True, default=())

    @classmethod
    def create(
        cls,
        system: AbstractSystem,
        data: Trajectories,
        *,
        trainable: Trainable = None,
        log_prior: Callable[[AbstractSystem], Any] | None = None,
        overrides: Overrides = (),
    ) -> tuple[FitProblem, Theta]:
        """The problem and the flat, unconstrained θ of ``system``'s trainable leaves.

        Raises:
            ValueError: naming the field, when a parameter lies outside its declared constraint
                (host-side; skipped for traced values); when ``trainable`` selects nothing.
        """
        check_constraints(system)
        overrides = tuple(overrides)
        mask = trainable_mask(system, trainable, overrides=overrides)
        params, static = eqx.partition(system, mask)
        constraints = tuple(_trainable_constraints(system, mask, overrides))
        # Strongly typed θ, template and fixed leaves: a weakly typed leaf (e.g. a noise scale
        # given as a Python float) would make the second epoch, whose θ comes back from a solver
        # strongly typed, compile again, and the problem's system a different program from the
        # promoted one the start states are smoothed with (the smoother traced twice).
        # A weak float acts in the system's dtype, so it is cast to that (exactly as before).
        dtype = float_dtype(system)
        static = jtu.tree_map(lambda a: _cast_weak(a, dtype), static)
        leaves, treedef = jtu.tree_flatten(params)
        unconstrained, back, theta = _unconstrained_leaves(constraints, leaves)
        template = jtu.tree_unflatten(treedef, unconstrained)
        if theta.size == 0:
            raise ValueError(
                "`trainable` selects no parameter to learn: it must pick at least one "
                "floating-point array of the system that is not declared `ceemx.param(fixed=True)`."
            )
        backs = [None] * len(leaves) if back is None else back
        for where, c, x, z, b in zip(
            _trainable_names(system, mask), constraints, leaves, unconstrained, backs, strict=True
        ):
            check_room(c, x, z, where, back=b)
        check_log_prior(log_prior, system)
        return cls(template, static, data, log_prior, constraints, overrides), theta

    def with_data(self, data: Trajectories) -> FitProblem:
        """This problem over other data of the same shape of model (θ's layout, prior kept).

        The data are all a problem holds of them: nothing else is rebuilt (the devices' copy of
        the data, or this process's copy of a multi-process fit's).
        """
        return eqx.tree_at(lambda p: p.data, self, data)

    def subset(self, keep) -> FitProblem:
        """This problem over the trajectories ``keep`` (indices into the batch) of its data."""
        return self.with_data(self.data[keep])

    def build(self, theta: Theta) -> AbstractSystem:
        """The system with trainable leaves set from the flat unconstrained vector θ.

        On the host (a concrete θ: the epoch loop, callbacks) one compiled program per problem
        structure; op by op it dispatched and, at each new shape, compiled a dozen small
        programs (unravel, constraints, casts: ≈ 1 ms per call in steady state, two calls per
        Algorithm-1 epoch).
        """
        if isinstance(theta, Tracer):
            return _build(self.template, self.static, self.constraints, theta)
        return _build_compiled(self.template, self.static, self.constraints, theta)

    def theta_of(self, system: AbstractSystem) -> Theta:
        """The flat, unconstrained θ of ``system`` (of this problem's structure).

        The inverse of :meth:`build`, e.g. for a model a callback kept from an earlier epoch.
        """
        mask = jtu.tree_map(lambda v: v is not None, self.template, is_leaf=lambda v: v is None)
        params, _ = eqx.partition(system, mask)
        leaves = jtu.tree_leaves(params)
        return _unconstrained_leaves(self.constraints, leaves)[2]

    def natural(self, theta: Theta) -> Float[Array, " theta"]:
        """The flat θ in natural units: each entry through its constraint's ``forward``."""
        if isinstance(theta, Tracer):
            return _natural(self.template, self.constraints, theta)[0]
        return _natural_compiled(self.template, self.constraints, theta)[0]

    def natural_jacobian(self, theta: Theta) -> Float[Array, " theta"]:
        """(P,) d natural / dθ, elementwise (every constraint acts entry by entry)."""
        if isinstance(theta, Tracer):
            return _natural(self.template, self.constraints, theta)[1]
        return _natural_compiled(self.template, self.constraints, theta)[1]

    def sign_definite(self, theta: Theta) -> np.ndarray:
        """(P,) bool: whether each entry's constraint keeps its natural value off zero's far side.

        True for :class:`Positive`, ``GreaterThan(lower ≥ 0)``, ``LessThan(upper ≤ 0)`` and an
        ``Interval`` that does not contain 0 in its interior: such a parameter never changes sign,
        so relative (log) changes are its natural unit. (The constraints decide, not θ's values.)
        """
        del theta
        leaves = jtu.tree_leaves(self.template)
        constraints = self.constraints or (Unconstrained(),) * len(leaves)
        flags = [
            np.full(np.size(z), _sign_definite(c), bool)
            for c, z in zip(constraints, leaves, strict=True)
        ]
        return np.concatenate(flags) if flags else np.zeros((0,), bool)

    def parameter_names(self) -> list[str]:
        """One name per entry of θ, as the user wrote the field: ``k``, ``H[2,3]``, ``sub.k``."""
        names = []
        for path, leaf in jtu.tree_flatten_with_path(self.template)[0]:
            base = jtu.keystr(path).removeprefix(".")
            shape = jnp.shape(leaf)
            if shape == ():
                names.append(base)
            else:
                names += [
                    f"{base}[{','.join(map(str, i))}]"
                    for i in itertools.product(*map(range, shape))
                ]
        return names

    def trains(self, field: str) -> bool:
        """Whether any leaf of the system's top-level ``field`` (e.g. ``"obs_noise"``) is in θ."""
        sub = getattr(self.template, field, None)
        return bool(jtu.tree_leaves(sub))

    def per_trajectory(
        self, theta: Theta, states: States, data: Trajectories | None = None
    ) -> PerTrajectory:
        """(B,) −J_b(x_b, θ), the negative log-likelihood of each trajectory (Eq. 9)."""
        data = self.data if data is None else data
        return jax.vmap(neg_log_joint_single, in_axes=(None, 0, 0, 0, 0))(
            self.build(theta), states, data.y, data.u, data.mask
        )

    def offset(self, theta: Theta, weights: PerTrajectory) -> Scalar:
        """Σ_b w_b·c_b, the x-independent constants of −J (see ``objective.nll_offset``).

        −J − offset is ½‖whitened residuals‖² for Gaussian noise: the scale of every relative
        tolerance (normalising constants can dwarf the fit).
        """
        c = nll_offset(self.build(theta), self.data)
        return jnp.sum(jnp.where(weights > 0, weights * c, 0.0))

    def neg_log_prior(self, theta: Theta) -> Scalar:
        """−log p(θ) (zero without a prior)."""
        if self.log_prior is None:
            return jnp.zeros((), theta.dtype)
        return -self.log_prior(self.build(theta))

    def prior_terms(
        self, theta: Theta
    ) -> tuple[Scalar, Float[Array, " theta"], Float[Array, "theta theta"]]:
        """(−log p(θ), its gradient, its symmetrised Hessian); zeros without a prior."""
        P = theta.shape[0]
        if self.log_prior is None:
            zero = jnp.zeros((), theta.dtype)
            return zero, jnp.zeros((P,), theta.dtype), jnp.zeros((P, P), theta.dtype)
        value, grad = jax.value_and_grad(self.neg_log_prior)(theta)
        return value, grad, symmetrize(jax.hessian(self.neg_log_prior)(theta))


@program(runs=Runs.ONCE)  # at a fit's start and end, once per epoch in Algorithm 1: cheap to run
def per_trajectory_nll(problem: FitProblem, theta: Theta, states: States) -> PerTrajectory:
    """(B,) −J_b(x_b, θ), compiled once per problem shape.

    Shared by the solvers and the health test: one program, not an op-by-op evaluation.
    """
    return problem.per_trajectory(theta, states)


@program(runs=Runs.ONCE)
def per_trajectory_offset(problem: FitProblem, theta: Theta) -> PerTrajectory:
    """(B,) the x-independent constants of −J_b (see :meth:`FitProblem.offset`), compiled."""
    return nll_offset(problem.build(theta), problem.data)
