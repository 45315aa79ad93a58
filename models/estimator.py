"""The one estimator contract of vslab, scikit-learn's: every fitted thing (clock fitters, registrations,
baselines, the hybrid networks) is an :class:`Estimator`.

- The constructor only stores its keyword parameters, unchanged (no work, no data, no validation);
  ``get_params`` / ``set_params`` / ``sklearn.base.clone`` work on them.
- ``fit(...)`` validates, learns attributes whose names end in ``_`` and returns ``self``.
- Using an estimator before ``fit`` raises :class:`models.errors.NotFittedError`.
- Randomness comes from a ``random_state`` (or ``seed``) parameter, never from global state.

Built on ``sklearn.base.BaseEstimator`` (parameters from the constructor's signature, ``clone``, the
``repr``) rather than a copy of it: scikit-learn is a dependency already (the baselines' regressors), and its
``clone`` is what the contract means. ``tests/test_estimator_contract.py`` runs one suite over every
estimator.
"""

from __future__ import annotations

from sklearn.base import BaseEstimator

from models.errors import NotFittedError


class Estimator(BaseEstimator):
    """Base of every fitted thing in vslab (see the module docstring for the contract)."""

    def fitted_attributes(self) -> list[str]:
        """The attributes ``fit`` learned (names ending in ``_``); empty before ``fit``."""
        return [k for k in vars(self) if k.endswith("_") and not k.startswith("_")]

    def check_fitted(self) -> None:
        """``NotFittedError`` unless ``fit`` has run."""
        if not self.fitted_attributes():
            raise NotFittedError(f"{type(self).__name__}: call fit() before using it")
