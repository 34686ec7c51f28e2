"""What a fit returns (:class:`FitResult`) and what its callbacks receive (:class:`EpochInfo`).

The analyses of a result (diagnostics, identifiability, uncertainty, summary) live in
:mod:`ceemx.identification.analysis`; :class:`FitResult` delegates to them, one line per method.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

import equinox as eqx
import numpy as np

from ceemx.identification.analysis.diagnostics import fit_diagnostics
from ceemx.identification.analysis.identifiability import Identifiability, fit_identifiability
from ceemx.identification.analysis.noise_check import NoiseCheck
from ceemx.identification.analysis.profile import Profile, fit_profile
from ceemx.identification.analysis.summary import fit_summary, noise_round_messages, short_repr
from ceemx.identification.analysis.uncertainty import (
    fit_covariance,
    fit_parameter_estimates,
    fit_standard_errors,
)
from ceemx.identification.problem import FitProblem
from ceemx.identification.saving import save
from ceemx.identification.solvers.base import AbstractFitSolver
from ceemx.lib.results import RESULTS, codes, messages
from ceemx.lib.typing import States
from ceemx.models.system import AbstractSystem

__all__ = ["EpochInfo", "FitResult"]


@dataclasses.dataclass
class EpochInfo:
    """What a callback receives after each epoch.

    Attributes:
        epoch: 1-based epoch number.
        system: the system after this epoch.
        states: (B, T, n) states after this epoch (in a multi-process fit a global array:
            read it with :func:`ceemx.infra.distributed.to_host`, on every process).
        record: this epoch's history record (a dict; callbacks may add entries to it).
    """

    epoch: int
    system: AbstractSystem
    states: States
    record: dict


class FitResult(eqx.Module):
    """The outcome of :func:`ceemx.fit`, the same for every solver.

    Attributes:
        system: the learned system.
        states: (B, T, n) state trajectories at the end.
        status: (B,) per-trajectory :class:`ceemx.RESULTS`.
        history: one dict per epoch. Keys every solver has: ``epoch``, ``time`` (seconds of the
            epoch), ``J`` (total log-likelihood, Eq. 9, over the trajectories taking part),
            ``J_before``, ``J_per_trajectory``, ``dtheta_norm``, ``dx_norm``,
            ``failed_trajectories``, ``converged``, ``stop``; plus the solver's own
            (``type(solver).history_keys``) and whatever callbacks returned (e.g. ``eps``).
        converged: whether the solver's stopping criterion was met (else ``max_epochs`` ran out,
            a callback stopped the fit, or every trajectory failed). With ``identifiability``
            stopped, it means converged in what the data determine.
        solver: the solver that produced it.
        initial_J: J at the initial (x, θ) (over the trajectories fitted).
        excluded: indices of the trajectories the start-of-fit health test excluded
            (:mod:`ceemx.identification.fitting.health`); their states are returned as given,
            their status is ``outlier``, and ``history`` covers the others only.
        start_mean_square: (B,) the health test's r_b, the mean squared whitened residual of
            each trajectory at the start (``None`` with ``outliers="keep"``).
        identifiability: the parameter combinations the data do not determine, named
            (:class:`~ceemx.identification.analysis.identifiability.Identifiability`: ``message``,
            ``determined`` such as ``("a·b", "a·c")``, ``stopped``), as the solver found them —
            :class:`ceemx.JointLM` during the fit; :class:`ceemx.Alternating` and JointLM at the
            end point of a fit that did not converge in 20 epochs or more — else ``None``;
            :meth:`check_identifiability` runs the analysis on demand.
        problem: the :class:`~ceemx.identification.problem.FitProblem` that was fitted (the
            trajectories taking part; ``None`` for results built by hand).
        theta: the final flat θ in the problem's unconstrained coordinates.
        weights: the final (B',) trajectory weights of the fitted trajectories (0: failed).
        noise_rounds: with ``fit(..., noise="learn")``, one record per noise round (``round``,
            ``process_noise_std``, ``obs_noise_std``: the noise that round's fit ran at, which
            the last round's is :attr:`system`'s; ``log_evidence``; ``floored`` and ``notes``:
            the floors from the data its estimate was held at; ``epochs``, ``converged``,
            ``change``: how far the estimate after the fit moved the factors; ``settled``;
            ``time``: seconds; round 0 is the estimate at the start; the last one also holds
            ``learned``: whether any estimate was not degenerate); else ``()``.
        noise_check: the end-of-fit noise check
            (:mod:`ceemx.identification.analysis.noise_check`): are the residuals consistent with
            the assumed noise? (``None`` with
            ``fit(..., diagnose=False)``, when no epoch ran, or for non-Gaussian noise.)
            :meth:`diagnostics` gives the full report.
        choice: the method that ran and why
            (:class:`~ceemx.identification.fitting.default_path.Choice`: its stages, each with
            its epochs, convergence and time, and the reason — the library's rule when ``fit``
            was given no solver, else "named by the user"); ``None`` for results built by hand.

    Parameter uncertainty (:mod:`ceemx.identification.analysis.uncertainty`): :meth:`covariance`,
    :meth:`standard_errors`, :meth:`parameter_estimates` — as the solver declares
    (``AbstractFitSolver.uncertainty``): for the CE methods the Laplace approximation of the joint
    posterior p(x, θ | y) (valid at a converged maximum of J); for :class:`ceemx.LaplaceEM` the
    inverse observed information of the Laplace log-evidence, the states integrated out (learned
    noise scales included).
    """

    system: AbstractSystem
    states: States
    status: RESULTS
    history: list = eqx.field(static=True)
    converged: bool = eqx.field(static=True)
    solver: AbstractFitSolver
    initial_J: float = eqx.field(static=True)
    excluded: tuple = eqx.field(static=True, default=())
    start_mean_square: tuple | None = eqx.field(static=True, default=None)
    identifiability: Identifiability | None = eqx.field(static=True, default=None)
    problem: FitProblem | None = None
    theta: Any = None
    weights: Any = None
    noise_check: NoiseCheck | None = eqx.field(static=True, default=None)
    noise_rounds: tuple = eqx.field(static=True, default=())
    choice: Any = eqx.field(static=True, default=None)

    @property
    def epochs(self) -> int:
        """Number of epochs run, including resumed ones."""
        return len(self.history)

    def history_array(self, name: str) -> np.ndarray:
        """One history entry across epochs as an array."""
        return np.asarray([h[name] for h in self.history])

    def messages(self) -> list[str]:
        """One status message per trajectory, consistent with :attr:`converged`.

        A trajectory whose solver status is ``successful`` in a fit that did not converge (the
        epoch bound ran out, a callback stopped it) reads "stopped before convergence". When the
        end-of-fit noise check failed, its message follows the per-trajectory ones.
        """
        out = messages(self.status)
        if not self.converged:
            ok = np.atleast_1d(codes(self.status)).reshape(-1) == int(codes(RESULTS.successful))
            out = [
                "stopped before convergence (max_epochs reached or stopped by a callback)"
                if good
                else text
                for good, text in zip(ok, out, strict=True)
            ]
        if self.identifiability is not None:  # what the data do not determine, after them
            out = [*out, self.identifiability.message]
        if self.noise_check is not None and self.noise_check.message:
            out = [*out, self.noise_check.message]
        if self.noise_rounds:  # noise="learn": the floors held, rounds that did not settle
            out = [*out, *noise_round_messages(self.noise_rounds)]
        return out

    def diagnostics(self, **options):
        """Residual and noise diagnostics of the fitted model on the fitted trajectories.

        :func:`~ceemx.identification.analysis.diagnostics.residual_diagnostics` at the end point
        (noise ratios and the noise the data say, the EKF prediction-error tests); ``options``
        are its keyword arguments (``lags``, ``estimate``, ``factor``, ``initial``).
        """
        return fit_diagnostics(self, **options)

    def check_identifiability(self) -> Identifiability | None:
        """:attr:`identifiability`, or the analysis at the end point when the fit found none.

        One joint linearisation and Schur complement (compiled once per problem shape) and a host
        eigen-analysis (:mod:`ceemx.identification.analysis.identifiability`); ``None`` when the
        data determine every parameter.
        """
        return fit_identifiability(self)

    def covariance(self, natural: bool = False, *, hold_weak: bool = False):
        """(P, P) Laplace covariance of the trainable θ (``analysis.uncertainty``).

        Args:
            natural: ``False`` (default): of the flat θ in the problem's unconstrained
                coordinates (``FitResult.theta``); ``True``: in natural units by the delta method.
            hold_weak: for the CE methods, when some entries are not determined by the data,
                the covariance of the others with those held at their estimates (NaN in the held
                rows), instead of NaN everywhere (:meth:`summary` uses it).

        Returns:
            The covariance; all NaN, with a warning, when the Schur complement is not positive
            definite (not at a maximum, or a parameter is not identifiable).
        """
        return fit_covariance(self, natural, hold_weak=hold_weak)

    def standard_errors(self):
        """Natural-unit standard errors (delta method), as a pytree like :attr:`system`.

        Each trainable leaf holds its standard errors (same shape); every other leaf is ``None``.
        """
        return fit_standard_errors(self)

    def parameter_estimates(self) -> dict[str, tuple[float, float]]:
        """``name → Estimate(estimate, std_error)`` per trainable scalar, in natural units.

        Each value is a named pair (``value, se = estimates["k"]`` still unpacks); ``print``
        shows the dict as a table.

        Names as written in the system (``sigma[0]``, ``A[0,1]``, ``process_noise.scale``); the
        key paths of earlier versions (``.A[0,1]``) still look up. The dict feeds
        :func:`ceemx.evaluation.report.estimate_table`.
        """
        return fit_parameter_estimates(self)

    def profile(self, name: str, *, level: float = 0.95, **options) -> Profile:
        """The profile-likelihood interval of one parameter (``analysis.profile``).

        The objective the fit maximised (J for the certainty-equivalent methods, the Laplace
        evidence for :class:`ceemx.LaplaceEM`), maximised again over the states and the other
        parameters with ``name`` held at each value; the ``level`` interval is where
        2·(max − profile) ≤ χ²₁(level) (3.841 at 95 %), beside the Wald interval. ``name`` as the
        summary names it (``k``, ``A[0,1]``); ``options``: ``max_epochs`` (of each refit),
        ``max_steps``, ``xtol``, ``solver``, ``grid`` (more points, for a figure:
        :func:`ceemx.evaluation.plots.plot_profile`)
        (:func:`~ceemx.identification.analysis.profile.fit_profile`). Each point is a refit.

        Example:
            >>> print(result.profile("c"))  # doctest: +SKIP
        """
        return fit_profile(self, name, level=level, **options)

    def summary(
        self,
        format: Literal["text", "markdown"] = "text",
        *,
        level: float = 0.95,
        diagnostics: bool = False,
        uncertainty: bool = True,
        max_rows: int | None = 40,
        intervals: Literal["auto", "wald", "profile"] = "auto",
    ) -> str:
        """What the fit found, for a person (:mod:`ceemx.identification.analysis.summary`).

        The trainable parameters in natural units, named as written (estimate, standard error,
        ``level`` interval, constraint), the noise models, J, data, epochs and time, status, the
        noise check and identifiability records, and the messages; ``diagnostics=True`` adds
        :meth:`diagnostics` (an EKF pass and a Laplace E-step, not run by default);
        ``uncertainty=False`` skips the covariance. ``format``: ``"text"`` or ``"markdown"``.
        ``intervals``: ``"auto"`` (default) prints profile-likelihood intervals (:meth:`profile`)
        for the few parameters near a bound or with a skewed objective (at most 3; the rule in
        :mod:`ceemx.identification.analysis.profile`), Wald for the others; ``"wald"`` computes
        no profile; ``"profile"`` profiles every parameter. Each interval says its kind.

        Example:
            >>> print(result.summary())  # doctest: +SKIP
        """
        return fit_summary(
            self,
            format,
            level=level,
            diagnostics=diagnostics,
            uncertainty=uncertainty,
            max_rows=max_rows,
            intervals=intervals,
        )

    def save(self, path, *, data=None):
        """Save the learned system with this fit's summary line and data metadata.

        :func:`ceemx.save` of this result (``ceemx.load(path)`` gives the system back, in this
        process or another). Returns the path written.
        """
        return save(path, self, data=data)

    def __repr__(self) -> str:
        """A few lines: solver, convergence, J and the first estimates (nothing computed)."""
        return short_repr(self)
