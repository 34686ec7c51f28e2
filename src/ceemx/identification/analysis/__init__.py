"""Post-fit analysis: what a fit found, how sure it is, and whether its noise fits the data.

- :mod:`~ceemx.identification.analysis.identifiability` — which parameter combinations the data
  determine (also the joint method's stopping rule);
- :mod:`~ceemx.identification.analysis.uncertainty` — the Laplace covariance of θ, standard
  errors;
- :mod:`~ceemx.identification.analysis.noise_check` — the end-of-fit noise check;
- :mod:`~ceemx.identification.analysis.noise_estimate` — the noise the data show (residual
  moments, :func:`~ceemx.identification.analysis.noise_estimate.estimate_noise`);
- :mod:`~ceemx.identification.analysis.diagnostics` — the residual diagnostics report;
- :mod:`~ceemx.identification.analysis.correlations` — residual auto- and input
  cross-correlations with their bands (MATLAB's ``resid``), from any residuals;
- :mod:`~ceemx.identification.analysis.summary` — the text summary of a fit.

:class:`ceemx.FitResult` delegates to these, one line per method. They read the fit problem, the
shared mathematics (:mod:`ceemx.identification.schur`, :mod:`ceemx.identification.noise_moments`)
and the inference layer; never the solvers or the fit machinery.
"""
