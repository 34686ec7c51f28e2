"""`ceemx.evaluation.paired_bootstrap`: the paired moving-block bootstrap behind `fit_hybrid`'s
choices (pure NumPy: known answers on synthetic error series)."""

from __future__ import annotations

import numpy as np
import pytest

from ceemx.evaluation.paired_bootstrap import adjusted_level, clearly_better, politis_block_length


def _ar1(phi: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """A stationary AR(1) series of unit variance."""
    e = rng.normal(size=n) * np.sqrt(1 - phi**2)
    x = np.empty(n)
    x[0] = rng.normal()
    for t in range(1, n):
        x[t] = phi * x[t - 1] + e[t]
    return x


def test_identical_errors_are_not_better():
    """The same errors: δ = 0 in every replicate, so the bound is 0 and B is not better."""
    e = np.random.default_rng(0).normal(size=(2, 300, 2))
    c = clearly_better(e, e.copy())
    assert not c.better
    assert c.improvement == 0.0 and c.lower_bound == 0.0 and c.n == 600


def test_clearly_smaller_iid_errors_are_better():
    """B's iid errors have 0.7× A's spread: δ ≈ 0.3, the bound well above 0, blocks of 1–2."""
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=800), 0.7 * rng.normal(size=800)
    c = clearly_better(a, b)
    assert c.better and 0.2 < c.lower_bound < c.improvement < 0.4
    assert c.block_length <= 2
    assert c.level == 0.95 and c.record()["n"] == 800
    reverse = clearly_better(b, a)  # A better than B: B not better
    assert not reverse.better and reverse.improvement < 0
    assert clearly_better(a, b) == c  # the seed fixes the result


def test_the_blocks_keep_an_autocorrelated_difference_from_looking_significant():
    """d = e²_A − e²_B an AR(1) with φ = 0.99 and a small positive mean: the iid bootstrap
    (blocks of 1) calls B better; the rule's blocks (hundreds of samples) do not."""
    rng = np.random.default_rng(0)
    n = 2000
    base = 2.0 + np.abs(rng.normal(size=n))
    d = 0.05 * _ar1(0.99, n, rng) + 0.01
    a, b = np.sqrt(base), np.sqrt(base - d)
    assert d.mean() > 0
    iid = clearly_better(a, b, block_length=1)
    blocks = clearly_better(a, b)
    assert iid.better and iid.lower_bound > 0
    assert not blocks.better and blocks.lower_bound < 0
    assert blocks.block_length > 50 and blocks.improvement == iid.improvement


def test_block_length_rule_reads_the_autocorrelation():
    """White noise: m̂ = 0, blocks of 1 (2 at most by chance); AR(1) with φ = 0.95 (ρ(k) =
    0.95^k, under the threshold only after tens of lags): blocks longer than 10; at most a
    third of the shortest series."""
    rng = np.random.default_rng(2)
    assert politis_block_length(rng.normal(size=2000)) <= 2
    assert politis_block_length(_ar1(0.95, 2000, rng)) > 10
    short = [_ar1(0.999, 60, rng), _ar1(0.999, 3000, rng)]
    assert politis_block_length(short) <= 20
    assert politis_block_length(np.zeros(100)) == 1  # no variation: iid


def test_masked_samples_are_left_out():
    """Entries off the mask do not count: a huge error of B there changes nothing; a step with
    no observed output is dropped from n."""
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(1, 400, 2)), 0.5 * rng.normal(size=(1, 400, 2))
    mask = np.ones_like(a, bool)
    mask[0, 100:150, :] = False  # 50 steps with no output observed
    mask[0, 200:260, 1] = False  # 60 steps with one output of two
    spoiled = b.copy()
    spoiled[~mask] = 1e6
    clean = clearly_better(a, b, mask=mask)
    assert clearly_better(a, spoiled, mask=mask) == clean
    assert clean.n == 350 and clean.better
    assert not clearly_better(a, spoiled).better


def test_nonfinite_errors_decide_without_resampling():
    """B diverged: not better; A diverged and B did not: better."""
    a = np.ones(50)
    b = np.full(50, 0.5)
    b[10] = np.inf
    assert not clearly_better(a, b).better
    assert clearly_better(b, a).better


@pytest.mark.parametrize("level", [0.0, 1.0, 1.5, -0.1, float("nan")])
def test_level_must_be_in_the_open_unit_interval(level):
    with pytest.raises(ValueError, match="`level` must be a number in \\(0, 1\\)"):
        clearly_better(np.ones(10), np.ones(10), level=level)


def test_shapes_must_match():
    with pytest.raises(ValueError, match="same shape"):
        clearly_better(np.ones(10), np.ones(11))
    with pytest.raises(ValueError, match="mask"):
        clearly_better(np.ones(10), np.ones(10), mask=np.ones(9, bool))


def test_the_best_of_many_equal_models_is_better_only_by_luck():
    """80 models as good as A: the best scores better by chance; its adjusted test says no.

    The winner's curse: the unadjusted 95 % test calls the best of 80 exchangeable candidates
    clearly better than the reference; at the Bonferroni level over the 80 it is not.
    """
    rng = np.random.default_rng(0)
    a = rng.normal(size=500)
    candidates = [0.9 * a + np.sqrt(1 - 0.81) * rng.normal(size=500) for _ in range(80)]
    best = min(candidates, key=lambda c: float(np.mean(c**2)))
    assert clearly_better(a, best).better
    assert adjusted_level(0.95, 80) == pytest.approx(1 - 0.05 / 80)
    assert adjusted_level(0.95, 1) == 0.95 and adjusted_level(0.95, 0) == 0.95
    strict = clearly_better(a, best, level=adjusted_level(0.95, 80))
    assert not strict.better and strict.lower_bound < 0
