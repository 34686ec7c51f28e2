"""Identification: θ (and the states) from data — the EM layer.

The fit problem (θ ⇄ system, −J, prior; :mod:`~ceemx.identification.problem`), the one driver
:func:`~ceemx.identification.driver.fit` and its :class:`FitResult`, the fit solvers
(:mod:`~ceemx.identification.solvers`: Algorithm 1, the joint method, Laplace EM, Particle EM),
the learning step (:mod:`~ceemx.identification.learning`), start states
(:mod:`~ceemx.identification.initialize`), the start-of-fit health test
(:mod:`~ceemx.identification.health`), parameter uncertainty
(:mod:`~ceemx.identification.uncertainty`) and identifiability — which parameter combinations
the data determine (:mod:`~ceemx.identification.identifiability`). Layer rule: may import
everything below it (lib, infra, models, data, systems, inference); never evaluation, baselines
or experiments.
"""
