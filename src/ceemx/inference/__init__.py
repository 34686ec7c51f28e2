"""Inference: every estimator of the hidden states at a fixed θ.

The objective they share — the joint log-density J(x, θ) of Eq. 9 and its Gauss–Newton
linearisation (:mod:`~ceemx.inference.objective`) — the MAP smoother of Eq. 10
(:mod:`~ceemx.inference.smoother`), the Gaussian (Laplace) posterior around it
(:mod:`~ceemx.inference.posterior`), the extended Kalman filter (:mod:`~ceemx.inference.ekf`) and
the particle filter with FFBSi (:mod:`~ceemx.inference.particle`). Layer rule: may import
:mod:`ceemx.lib`, :mod:`ceemx.infra`, :mod:`ceemx.models`, :mod:`ceemx.data`; never
identification or evaluation.
"""
