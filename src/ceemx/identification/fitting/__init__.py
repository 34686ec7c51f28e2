"""The fit machinery: :func:`~ceemx.identification.fitting.driver.fit` and its :class:`FitResult`.

A fit reads as three steps, one module each, around the solver's ``init / step / terminate /
postprocess`` (:mod:`ceemx.identification.solvers`):

- :mod:`~ceemx.identification.fitting.start` — the fit problem, the start states, the
  start-of-fit health test (:mod:`~ceemx.identification.fitting.health`), the solver's first
  state or a resumed checkpoint;
- :mod:`~ceemx.identification.fitting.epochs` — the epoch loop: history, callbacks, progress,
  checkpoints;
- :mod:`~ceemx.identification.fitting.finish` — the end point, the excluded trajectories, the
  noise check, the :class:`~ceemx.identification.fitting.result.FitResult`.

:mod:`~ceemx.identification.fitting.run` composes them; :mod:`~.noise_rounds` runs rounds of it
with the noise the data show (``fit(..., noise="learn")``); :mod:`~.choice` chooses the method of
a ``fit`` without a solver from the problem and :mod:`~.default_path` runs its stages as one
result; :mod:`~.driver` holds the public :func:`~ceemx.identification.fitting.driver.fit`. The
machinery asks the solvers what they can do (their class-level capabilities); only the rule in
:mod:`~.choice` names concrete solvers.
"""
