"""ceemx: certainty-equivalent EM for partially observed nonlinear dynamical systems, in JAX.

The package reads as the pipeline, one folder a stage (a lower folder never imports a higher one;
``.ci/check_imports.py`` enforces it): :mod:`ceemx.lib` (maths that knows nothing of EM) and
:mod:`ceemx.infra` (checkpoints, compilation cache, threads) at the bottom; :mod:`ceemx.models`,
:mod:`ceemx.data`, :mod:`ceemx.systems`, :mod:`ceemx.datasets` (what goes in);
:mod:`ceemx.inference` (state estimators at fixed θ); :mod:`ceemx.identification` (θ: the fit
machinery, its solvers and learners, post-fit analysis); :mod:`ceemx.evaluation` (simulation,
prediction, scores, reports); :mod:`ceemx.baselines`, :mod:`ceemx.experiments` and the CLI on top.

The public names are listed once, in ``__init__.pyi`` (what type checkers read); ``import ceemx``
is light: ``lazy_loader`` reads that table and loads each name's module on first use, so the
``ceemx`` command can install its interrupt handler and answer ``--help`` before JAX is imported.
"""

from importlib.metadata import PackageNotFoundError, version

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)

try:
    __version__ = version("ceemx")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"
