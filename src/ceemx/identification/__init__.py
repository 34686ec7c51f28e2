"""Identification: θ (and the states) from data — the EM layer, by role.

- the problem and the mathematics the solvers share: :mod:`~ceemx.identification.problem`
  (θ ⇄ system, −J, prior), :mod:`~ceemx.identification.schur` (the joint Schur complement),
  :mod:`~ceemx.identification.noise_moments` (noise statistics and their closed-form update),
  :mod:`~ceemx.identification.initialize` (start states);
- the learning step (:mod:`~ceemx.identification.learning`) and the fit solvers
  (:mod:`~ceemx.identification.solvers`: Algorithm 1, the joint method, Laplace EM, Particle EM);
- post-fit analysis (:mod:`~ceemx.identification.analysis`: identifiability, uncertainty, noise
  check and estimate, diagnostics, summary);
- the fit machinery (:mod:`~ceemx.identification.fitting`: :func:`ceemx.fit` and its
  :class:`ceemx.FitResult`), and the hybrid-model builder
  (:mod:`~ceemx.identification.hybrid_builder`).

Layer rule: may import everything below it (lib, infra, models, data, systems, inference); never
evaluation, baselines or experiments.
"""
