"""Helpers of the tests of refusals: a model that counts the traces of its methods, and ``raises``.

A refusal must come before any compute: the ``no_compute`` fixture (tests/conftest.py) fails a
test in which the methods of a ``decay_class`` model were traced more than once (the one trace
allowed is the check of their output shapes, ``ceemx.models.method_check``: abstract
evaluation, nothing compiled or computed).
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from jaxtyping import Array

import ceemx

#: The methods of the counting models traced so far (cleared by ``no_compute``).
TRACES: list[str] = []


def decay_class():
    """A new class per call, so that no compiled program is reused from an earlier test."""

    class Decay(ceemx.AbstractSystem):
        """x' = a·x + w, y = c·x + v, one parameter per kind of bound; counts traces."""

        a: Array = ceemx.param(lower=-1.0, upper=1.0)
        c: Array = ceemx.param(positive=True)
        d: Array = ceemx.param(upper=-2.0)

        @property
        def state_dim(self):
            return 1

        @property
        def obs_dim(self):
            return 1

        def dynamics(self, x, u, t):
            TRACES.append("dynamics")
            return self.a * x + 0.0 * self.d

        def observe(self, x, u, t):
            TRACES.append("observe")
            return self.c * x

    return Decay


B, T = 2, 6
DATA = ceemx.Trajectories(np.random.default_rng(0).standard_normal((B, T, 1)))
X0 = np.zeros((B, T, 1))


def decay(a=0.5, c=1.0, d=-3.0):
    return decay_class()(a=a, c=c, d=d, process_noise=0.3, obs_noise=0.3)


def raises(exc, match):
    """``exc`` whose message contains ``match``.

    Where jaxtyping + beartype check the annotations of every ceemx ``__init__`` (the slow run in
    CI, ``--jaxtyping-packages``), a value of the wrong type (``rtol="abc"``) is their
    ``TypeError`` first, naming the parameter as 'rtol'; users get ceemx's own message.
    """
    if exc is TypeError and match.startswith("`"):
        name = match[1 : match.index("`", 1)]
        rest = re.escape(match[match.index("`", 1) + 1 :])
        return pytest.raises(TypeError, match=f"`{re.escape(name)}`{rest}|parameter '{name}'")
    return pytest.raises(exc, match=re.escape(match))
