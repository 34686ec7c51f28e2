"""Is one model's free run clearly better than another's on the same record? A block bootstrap.

:func:`clearly_better` compares two models by their free-run errors on the *same* samples (a
validation tail, or the training record itself). The statistic is the relative RMSE
improvement of model B over model A,

    δ = 1 − RMSE_B / RMSE_A,

and B is *clearly better* when the one-sided lower confidence bound of δ at ``level`` (0.95) is
above zero. The bound is a percentile bootstrap: the per-sample squared errors of the two models
are resampled together (paired: the same time steps for both, so what the record shares — a
hard stretch, an input both models mis-track — cancels), and the ``1 − level`` quantile of δ over
the replicates is the bound.

**Why blocks.** A free run's errors are strongly autocorrelated: a model that drifts off stays
off for hundreds of samples. An iid bootstrap treats every sample as new evidence and is
overconfident (a few per cent on a short tail come out "significant"). The circular
moving-block bootstrap (Künsch 1989; Politis & Romano 1992) resamples blocks of consecutive
samples instead, each block wrapping around the end of its trajectory; the blocks never cross
from one trajectory into another.

**The block length, from the data.** With d_t = e²_A,t − e²_B,t (the paired difference, whose
mean decides the test) and n its samples, the rule of Politis (2003, "Adaptive bandwidth choice",
J. Nonparametric Statistics 15, 517–533) — the starting point of the flat-top lag-window rule of
Politis & White (2004, "Automatic block-length selection for the dependent bootstrap",
Econometric Reviews 23, 53–70) — finds the lag m̂ where the autocorrelation of d dies out: the
smallest m after which K_n = max(5, ⌈√log₁₀ n⌉) consecutive sample autocorrelations
ρ̂(m+1), …, ρ̂(m+K_n) all lie within ±2·√(log₁₀ n / n). The block length is max(1, 2 m̂), at
most a third of the shortest trajectory (so that every trajectory has at least three blocks to
draw). White noise gives m̂ = 0 (blocks of one sample, the iid bootstrap); an AR(1) with φ = 0.95
gives m̂ of tens. With several trajectories the autocorrelation is pooled: lag products are
summed within each trajectory, never across two.

Several outputs: the per-step error is the mean over the observed outputs of the squared
errors (masked entries left out; a step with no observed output is dropped), so with no mask
RMSE² is the mean of the series, as :meth:`ceemx.EarlyStopping.score` computes it. The result is
reproducible (a fixed ``seed``); pure NumPy, outside JAX.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from jaxtyping import ArrayLike

from ceemx.infra.options import check_int, check_level

__all__ = ["REPLICATES", "PairedComparison", "adjusted_level", "clearly_better",
           "politis_block_length"]  # fmt: skip

#: the bootstrap replicates at the usual levels (more where the level asks for a far quantile)
REPLICATES = 2000


def adjusted_level(level: float, compared: int) -> float:
    """The level of one test where the better model was picked from ``compared`` candidates.

    The winner's curse: the best of several models scores well partly by chance, so its test
    against a reference is held to the Bonferroni level 1 − (1 − ``level``)/``compared`` — the
    chance that any of the candidates beats the reference by luck alone stays below 1 − level.
    """
    return 1.0 - (1.0 - level) / max(1, int(compared))


@dataclass(frozen=True)
class PairedComparison:
    """The result of :func:`clearly_better`.

    Attributes:
        better: whether B is clearly better than A (``lower_bound > 0``).
        improvement: δ = 1 − RMSE_B / RMSE_A on the samples (1: B exact; −inf: B not finite).
        lower_bound: the one-sided lower confidence bound of δ at ``level``.
        level: the confidence level.
        block_length: the bootstrap's block length (samples).
        n: the samples compared (time steps with an observed output, over every trajectory).
    """

    better: bool
    improvement: float
    lower_bound: float
    level: float
    block_length: int
    n: int

    def record(self) -> dict[str, Any]:
        """The comparison as plain Python values (for JSON)."""
        return asdict(self)


def _series(errors: ArrayLike, mask: ArrayLike | None, name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(e² averaged over the observed outputs per step (B, T), observed steps (B, T))``."""
    e = np.asarray(errors, dtype=np.float64)
    if e.ndim not in (1, 2, 3) or e.size == 0:
        raise ValueError(f"`{name}` must be a non-empty (T,), (B, T) or (B, T, m) array.")
    shape = {1: (1, e.size, 1), 2: e.shape + (1,), 3: e.shape}[e.ndim]
    m = np.ones(e.shape, bool) if mask is None else np.asarray(mask, bool)
    if m.shape != e.shape:
        raise ValueError(f"`mask` must have the shape of `{name}`, {e.shape}; got {m.shape}.")
    e, m = e.reshape(shape), m.reshape(shape)
    count = m.sum(axis=2)
    sq = np.where(m, e, 0.0) ** 2
    with np.errstate(invalid="ignore"):
        per_step = sq.sum(axis=2) / np.maximum(count, 1)
    return per_step, count > 0


def _autocorrelation(d: list[np.ndarray], max_lag: int) -> np.ndarray:
    """ρ̂(1 … max_lag) of the trajectories' series ``d``, pooled (lags within a trajectory).

    Lag products by FFT (zero-padded, so none wraps around), summed over the trajectories,
    over the pooled variance.
    """
    n = sum(len(x) for x in d)
    mean = sum(float(x.sum()) for x in d) / n
    gamma = np.zeros(max_lag + 1)
    for x in d:
        c = x - mean
        size = 1 << (2 * len(c) - 1).bit_length()
        f = np.fft.rfft(c, size)
        lags = np.fft.irfft(f * np.conj(f), size)[: min(len(c), max_lag + 1)]
        gamma[: len(lags)] += lags
    if not gamma[0] > 0 or not math.isfinite(gamma[0]):
        return np.zeros(max_lag)
    return gamma[1:] / gamma[0]


def politis_block_length(d: list[np.ndarray] | np.ndarray) -> int:
    """The block length max(1, 2 m̂) of the series ``d`` by Politis' rule (module notes).

    ``d``: one series, or a list of the trajectories' series (the autocorrelation pooled).
    At most a third of the shortest series (at least 1).
    """
    parts = [np.asarray(x, np.float64).ravel() for x in (d if isinstance(d, list) else [d])]
    n = sum(len(x) for x in parts)
    cap = max(1, min(len(x) for x in parts) // 3)
    if n < 3 or cap == 1:
        return 1
    K = max(5, math.ceil(math.sqrt(math.log10(n))))
    threshold = 2.0 * math.sqrt(math.log10(n) / n)
    max_lag = min(max(len(x) for x in parts) - 1, cap // 2 + K)
    small = np.abs(_autocorrelation(parts, max_lag)) < threshold  # small[k - 1]: |ρ̂(k)| small
    m_hat = next(
        (m for m in range(0, max_lag - K + 1) if small[m : m + K].all()), cap // 2
    )  # none within the lags that the cap allows: the cap
    return int(min(max(1, 2 * m_hat), cap))


def _replicate_sums(
    x: np.ndarray, length: int, rng: np.random.Generator, replicates: int
) -> np.ndarray:
    """Sums of ``x`` (columns: the two models) over circular block resamples of its length.

    ``ceil(n / length)`` blocks of ``length`` consecutive samples from uniform starts, wrapping
    at the end; the last block cut so the resample has n samples. Block sums by prefix sums,
    (replicates, 2).
    """
    n = len(x)
    length = min(length, n)
    k = -(-n // length)
    doubled = np.concatenate([x, x])
    prefix = [np.concatenate([[0.0], np.cumsum(doubled[:, j])]) for j in (0, 1)]
    sizes = np.full(k, length)
    sizes[-1] = n - (k - 1) * length
    chunk = max(1, _DRAWS // k)  # replicates at a time: at most ~_DRAWS block starts in memory
    out = []
    for r in range(0, replicates, chunk):
        starts = rng.integers(0, n, size=(min(chunk, replicates - r), k))
        ends = starts + sizes
        out.append(np.stack([(p[ends] - p[starts]).sum(axis=1) for p in prefix], axis=1))
    return np.concatenate(out)


#: Block starts drawn at a time (memory: 16 bytes per start per model).
_DRAWS = 1 << 20


def _improvement(sum_a, sum_b):
    """δ = 1 − sqrt(sum_b / sum_a) (sums of squared errors over the same samples)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(sum_a > 0, sum_b / np.where(sum_a > 0, sum_a, 1.0), np.inf)
        ratio = np.where((sum_a == 0) & (sum_b == 0), 1.0, ratio)
        return 1.0 - np.sqrt(ratio)


def _check(level, replicates, block) -> float:
    """``level`` as a float, the counts checked; or raise naming the argument."""
    level = check_level("level", level)
    if replicates is not None:
        check_int("replicates", replicates, 1)
    if block is not None:
        check_int("block_length", block, 1)
    return level


def clearly_better(
    errors_a: ArrayLike,
    errors_b: ArrayLike,
    *,
    mask: ArrayLike | None = None,
    level: float = 0.95,
    replicates: int | None = None,
    seed: int = 0,
    block_length: int | None = None,
) -> PairedComparison:
    """Whether model B's free-run errors are clearly smaller than model A's (module notes).

    Args:
        errors_a: A's errors on the samples, (T,), (B, T) or (B, T, m) (trajectories, steps,
            outputs; signed or not: they are squared).
        errors_b: B's errors on the same samples, the same shape.
        mask: which entries are observed (``True``), the errors' shape; ``None``: all.
        level: the one-sided confidence level of the lower bound, in (0, 1).
        replicates: bootstrap replicates (``None``: 2,000, or 20 / (1 − ``level``) where that
            is more, so that the bound's quantile has 20 replicates below it).
        seed: the resampling's seed (the result is a function of the data and the seed).
        block_length: blocks of this many samples instead of the rule's (1: the iid bootstrap).

    Returns:
        A :class:`PairedComparison`. B is not better when its errors are not finite; B is
        better (δ = 1) when A's are not finite and B's are.

    Raises:
        ValueError: a ``level`` outside (0, 1), shapes that differ, no observed sample.
    """
    level = _check(level, replicates, block_length)
    if np.shape(errors_a) != np.shape(errors_b):
        raise ValueError(
            f"`errors_a` and `errors_b` must have the same shape; got {np.shape(errors_a)} "
            f"and {np.shape(errors_b)}."
        )
    sa, keep = _series(errors_a, mask, "errors_a")
    sb, _ = _series(errors_b, mask, "errors_b")
    pairs = [np.stack([sa[i][keep[i]], sb[i][keep[i]]], axis=1) for i in range(len(sa))]
    pairs = [p for p in pairs if len(p)]
    if not pairs:
        raise ValueError("no observed sample to compare (`mask` is all False).")
    n = sum(len(p) for p in pairs)
    fa, fb = (bool(np.all(np.isfinite(np.concatenate([p[:, j] for p in pairs])))) for j in (0, 1))
    if not (fa and fb):
        delta = 1.0 if fb else -math.inf
        return PairedComparison(fb, delta, delta, level, 1, n)
    total = np.concatenate(pairs).sum(axis=0)
    delta = float(_improvement(total[0], total[1]))
    if block_length is None:
        length = politis_block_length([p[:, 0] - p[:, 1] for p in pairs])
    else:
        length = int(block_length)
    if replicates is None:
        replicates = max(REPLICATES, math.ceil(20.0 / (1.0 - level)))
    rng = np.random.default_rng(seed)
    sums = np.sum([_replicate_sums(p, length, rng, replicates) for p in pairs], axis=0)
    bound = float(np.quantile(_improvement(sums[:, 0], sums[:, 1]), 1.0 - level))
    return PairedComparison(bound > 0, delta, bound, level, length, n)
