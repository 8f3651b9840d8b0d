"""Input checks shared by the estimators: 2-D rows of the width they were fitted on.

numpy inputs go through scikit-learn's ``validate_data`` (finite, 2-D, floating point,
``n_features_in_`` set on fit and checked after); Dask arrays are checked by shape only,
since reading them to check values would cost a pass (the build checks its sources as it
reads them).
"""

from __future__ import annotations

import dask.array as da
import numpy as np
from sklearn.base import BaseEstimator
from sklearn.utils.validation import validate_data


def check_rows(est: BaseEstimator, X, reset: bool) -> np.ndarray | da.Array:
    """``X`` validated for ``est``; ``reset`` (a fit) records its width, otherwise it must match."""
    if isinstance(X, da.Array):
        if X.ndim != 2:
            raise ValueError(f"Expected a 2-D array of rows, got {X.ndim}-D")
        if reset:
            est.n_features_in_ = X.shape[1]
        elif X.shape[1] != getattr(est, "n_features_in_", X.shape[1]):
            raise ValueError(f"X has {X.shape[1]} features, but {type(est).__name__} is expecting "
                             f"{est.n_features_in_} features as input.")
        return X
    return validate_data(est, X, reset=reset, dtype=[np.float32, np.float64])
