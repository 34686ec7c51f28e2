"""The paper's baselines (§4.2.2): naive and H25 regressors, the LSTM, and subspace identification.

All are :class:`ceemx.prediction.AbstractPredictor`s (one-step predictions from the inputs) or, for
SID, linear state-space systems predicted by the Kalman filter.
"""

from .lstm import LSTMRegressor
from .regressors import LagRegressor, lag_windows
from .training import TrainInfo, fit_lag, fit_lstm, fit_naive, train_regressor

try:
    from .sid import fit_sid
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
