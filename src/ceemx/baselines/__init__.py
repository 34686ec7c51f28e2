"""The paper's baselines (§4.2.2): naive and H25 regressors, the LSTM, and subspace identification.

All are :class:`ceemx.evaluation.prediction.AbstractPredictor`s (one-step predictions from the
inputs) or, for SID, linear state-space systems predicted by the Kalman filter.
"""

from ceemx.baselines.lstm import LSTMRegressor
from ceemx.baselines.regressors import LagRegressor, lag_windows
from ceemx.baselines.training import TrainInfo, fit_lag, fit_lstm, fit_naive, train_regressor

try:
    from ceemx.baselines.sid import fit_sid
except ImportError:  # pragma: no cover - written separately
    pass

__all__ = [
    "LSTMRegressor",
    "LagRegressor",
    "TrainInfo",
    "fit_lag",
    "fit_lstm",
    "fit_naive",
    "fit_sid",
    "lag_windows",
    "train_regressor",
]
