"""Evaluation: what an identified model is worth, and how it is shown.

Free-run simulation and k-step prediction (:mod:`~ceemx.evaluation.simulation`), initial-state
estimation (:mod:`~ceemx.evaluation.initial_state`), one-step predictors
(:mod:`~ceemx.evaluation.prediction`), scores, ε(θ) and fit callbacks
(:mod:`~ceemx.evaluation.metrics`), and tables, files and figures (:mod:`~ceemx.evaluation.report`,
:mod:`~ceemx.evaluation.plots`). Layer rule: may import every layer below (lib to
identification); baselines, experiments and the CLI build on it.
"""
