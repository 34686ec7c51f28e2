"""The paper's baselines (§4.2.2): naive and H25 regressors, the LSTM, and subspace identification.

Beyond the paper: :func:`black_box`, the route for a record without physics (N4SID → CE-EM
linear model → neural state space, each model taking the raw inputs).

All are :class:`ceemx.evaluation.prediction.AbstractPredictor`s (one-step predictions from the
inputs) or, for SID, linear state-space systems predicted by the Kalman filter.
"""

from ceemx.baselines.black_box import BlackBox, black_box
from ceemx.baselines.lstm import LSTMRegressor
from ceemx.baselines.recipes import fit_lag, fit_lstm, fit_naive
from ceemx.baselines.regressors import LagRegressor, lag_windows
from ceemx.baselines.sid import fit_affine_sid, fit_sid, refine_linear, with_constant_input
from ceemx.baselines.training import TrainInfo, train_regressor

__all__ = [
    "BlackBox",
    "LSTMRegressor",
    "LagRegressor",
    "TrainInfo",
    "black_box",
    "fit_affine_sid",
    "fit_lag",
    "fit_lstm",
    "fit_naive",
    "fit_sid",
    "lag_windows",
    "refine_linear",
    "train_regressor",
    "with_constant_input",
]
