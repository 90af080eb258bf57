"""The scikit-learn estimator contract of the offline calibrators.

``__init__`` stores its settings exactly as given (no validation, no conversion); ``fit`` validates
them, does the work and returns ``self``; fitted results end in ``_`` (``result_``, ``R_``, ``b_``,
``calibration_``); ``get_params`` and ``set_params`` read and change the settings; using a result
before ``fit`` raises ``NotFittedError``. ``fit`` accepts a numpy array or a pandas DataFrame alike.
"""

from __future__ import annotations

import inspect

__all__ = ["Calibrator", "NotFittedError"]


class NotFittedError(ValueError, AttributeError):
    """A fitted result was asked for before ``fit`` (a ValueError and an AttributeError, as in scikit-learn)."""


class Calibrator:
    """Base class: settings are the ``__init__`` parameters; the fitted result is ``result_``."""

    @classmethod
    def _param_names(cls) -> list[str]:
        return [p for p in inspect.signature(cls.__init__).parameters if p != "self"]

    def get_params(self, deep: bool = True) -> dict:
        """The settings, by name.

        Parameters
        ----------
        deep : bool, optional
            Accepted for scikit-learn's contract; the settings hold no estimators.

        Returns
        -------
        dict
            Setting name -> value, as given.
        """
        return {name: getattr(self, name) for name in self._param_names()}

    def set_params(self, **params) -> Calibrator:
        """Change settings; returns ``self``.

        Parameters
        ----------
        **params
            Settings by name, stored as given (``fit`` checks them).

        Returns
        -------
        Calibrator
            ``self``.

        Raises
        ------
        ValueError
            An unknown setting's name.
        """
        known = self._param_names()
        for name, value in params.items():
            if name not in known:
                raise ValueError(f"{type(self).__name__} has no setting {name!r}; settings: {', '.join(known)}")
            setattr(self, name, value)
        return self

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items())
        return f"{type(self).__name__}({args})"

    @property
    def result_(self):
        """The fitted result; ``NotFittedError`` before ``fit``."""
        try:
            return self._result
        except AttributeError:
            raise NotFittedError(f"{type(self).__name__} is not fitted yet: call fit() first") from None

    @property
    def calibration_(self):
        """The fitted calibration (``magkf.Calibration``)."""
        return self.result_.to_calibration()

    @property
    def R_(self):
        """Fitted ``R`` of ``m = R B + b``: (3, 3), or (2, 2) for an ellipse."""
        return self.result_.R

    @property
    def b_(self):
        """Fitted ``b`` of ``m = R B + b`` in the data's units: (3,), or (2,) for an ellipse."""
        return self.result_.b
