"""Evaluation: what an identified model is worth, and how it is shown.

Free-run simulation, initial-state estimation and k-step prediction
(:mod:`~ceemx.evaluation.simulation`), one-step predictors (:mod:`~ceemx.evaluation.prediction`),
scores, ε(θ) and fit callbacks (:mod:`~ceemx.evaluation.metrics`), and tables, files and figures
(:mod:`~ceemx.evaluation.report`). Layer rule: may import every layer below (lib to
identification); baselines, experiments and the CLI build on it.
"""
