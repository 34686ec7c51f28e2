"""Per-fit bounds and fixed values (``fit(..., bounds=..., fixed=...)``) without editing the class.

Fast: the overrides themselves (values set, constraints by name, what θ holds, every refusal).
Slow: a fit whose bounded parameter stays inside its per-fit interval and whose fixed ones do not
move, on the named solver and on the default path.
"""

import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import Array

import ceemx
from ceemx.identification.fitting.overrides import apply_overrides
from ceemx.identification.problem import trainable_mask
from ceemx.models.constraints import (
    Fixed,
    GreaterThan,
    Interval,
    LessThan,
    Positive,
)
from ceemx.models.parameter_meta import entry_labels, leaf_constraints_with


class Decay(ceemx.AbstractSystem):
    """x⁺ = a x + b u, y = c x; a positive (class constraint), c an observation gain."""

    a: Array = ceemx.param(positive=True, unit="1", description="level kept per sample")
    b: Array = ceemx.param(unit="V/V")
    c: Array = ceemx.param()
    g: Array = ceemx.param(fixed=True, default=1.0)

    @property
    def state_dim(self):
        return 1

    @property
    def obs_dim(self):
        return 1

    @property
    def input_dim(self):
        return 1

    def dynamics(self, x, u, t):
        return self.g * self.a * x + self.b * u

    def observe(self, x, u, t):
        return self.c * x


def start():
    return Decay(
        jnp.array(0.5), jnp.array([0.3]), jnp.array(2.0), process_noise=0.01, obs_noise=0.01
    )


def test_overrides_set_values_and_constraints():
    system, overrides = apply_overrides(
        start(), bounds={"a": (0.1, 0.8), "b": (None, 1.0)}, fixed={"c": 1.0}
    )
    assert float(system.c) == 1.0 and float(system.a) == 0.5  # fixed set, the rest as given
    assert dict(overrides) == {"a": Interval(0.1, 0.8), "b": LessThan(1.0), "c": Fixed()}
    every = dict(
        zip(["a", "b", "c", "g"], leaf_constraints_with(system, overrides)[-4:], strict=True)
    )
    assert every["a"] == Interval(0.1, 0.8) and every["g"] == Fixed()
    mask = trainable_mask(system, overrides=overrides)
    assert (np.all(mask.a), np.all(mask.b), np.any(mask.c), np.any(mask.g)) == (
        True,
        True,
        False,
        False,
    )
    # None keeps the current value; one open end each way; (None, None) frees a class bound
    system, overrides = apply_overrides(start(), bounds={"a": (0.2, None)}, fixed={"c": None})
    assert float(system.c) == 2.0
    assert dict(overrides) == {"a": GreaterThan(0.2), "c": Fixed()}
    assert leaf_constraints_with(start(), ())[-4] == Positive()


def test_units_and_descriptions_per_entry():
    """``ceemx.param(unit=, description=)``: one label per entry of θ, fixed fields left out."""
    from ceemx.identification.problem import FitProblem

    data = ceemx.Trajectories.from_arrays(np.zeros(10), np.zeros(10))
    system, overrides = apply_overrides(start(), None, {"c": None})
    problem, _ = FitProblem.create(system, data, overrides=overrides)
    assert entry_labels(problem.template, system) == [("1", "level kept per sample"), ("V/V", "")]
    with pytest.raises(TypeError, match="`unit` must be a string"):
        ceemx.param(unit=3)


@pytest.mark.parametrize(
    ("bounds", "fixed", "says"),
    [
        ({"a": (-1.0, 1.0)}, None, "reaches outside its class's constraint (> 0"),
        ({"a": (0.6, 1.0)}, None, "does not contain its start value 0.5"),
        ({"a": (0.8, 0.2)}, None, "lower 0.8 must be below upper 0.2"),
        ({"a": 0.5}, None, "must be a pair (lower, upper)"),
        ({"g": (0.0, 2.0)}, None, "'g' is declared fixed in its class"),
        ({"k": (0.0, 1.0)}, None, "the system has no parameter 'k' (its parameters: "),
        (None, {"b[0]": 0.0}, "'b[0]' is one element of 'b'"),
        (None, {"a": -0.5}, "lies outside its class's constraint"),
        (None, {"b": [1.0, 2.0]}, "has shape (2,); the parameter's is (1,)"),
        ({"a": (0.1, 0.9)}, {"a": 0.5}, "'a' is both bounded and fixed"),
        ([("a", (0, 1))], None, "`bounds` must be a dict"),
    ],
)
def test_override_refusals(bounds, fixed, says):
    with pytest.raises((ValueError, TypeError)) as e:
        apply_overrides(start(), bounds, fixed)
    assert says in str(e.value), str(e.value)


def test_fit_refuses_before_any_compute(no_compute):
    del no_compute
    data = ceemx.Trajectories.from_arrays(np.zeros(10), np.zeros(10))
    with pytest.raises(ValueError, match="one element of 'b'"):
        ceemx.fit(start(), data, solver=ceemx.JointLM(), fixed={"b[0]": 0.0})


def record(T=60, seed=0):
    rng = np.random.default_rng(seed)
    u = rng.uniform(0.0, 1.0, T)
    x = np.zeros(T)
    for t in range(T - 1):
        x[t + 1] = 0.9 * x[t] + 0.1 * u[t]
    return ceemx.Trajectories.from_arrays(x + 0.01 * rng.standard_normal(T), u)


@pytest.mark.slow  # two fits of a one-state model
def test_bounded_and_fixed_fit():
    """The truth has a = 0.9; bounded to (0, 0.8) the estimate stays inside and ends at the
    bound; c fixed at 1 (a free c would trade off against b) stays 1 bit for bit, on the named
    solver and on the default path; the summary names the per-fit constraint."""
    data = record()
    kwargs = dict(bounds={"a": (0.0, 0.8)}, fixed={"c": 1.0}, max_epochs=50)
    named = ceemx.fit(
        start(), data, solver=ceemx.JointLM(), noise="fixed", diagnose=False, **kwargs
    )
    assert 0.79 < float(named.system.a) < 0.8
    assert float(named.system.c) == 1.0 and float(named.system.g) == 1.0
    text = named.summary(uncertainty=False)
    assert "in (0, 0.8)" in text and "a: level kept per sample" in text
    assert text.splitlines()[2].split() == [
        "parameter", "estimate", "unit", "std.", "error", "95", "%", "interval", "constraint"
    ]  # fmt: skip
    with pytest.warns(UserWarning, match="weakly determined: a"):  # a sits on its bound
        assert set(named.parameter_estimates()) == {"a", "b[0]"}
    free = ceemx.fit(start(), data, **{**kwargs, "bounds": {"a": (0.0, 0.95)}})
    assert float(free.system.c) == 1.0
    assert float(free.system.a) == pytest.approx(0.9, abs=0.02)  # inside: the truth
