"""The one exception base of vslab and the errors of its lowest layer.

Every error vslab raises on purpose derives from :class:`VslabError`, through one base per layer:
``ModelError`` (here), ``AcquisitionError`` (``acquisition/errors.py``), ``PipelineError``
(``pipeline/errors.py``) and ``CommandLineError`` (``vslab/app.py``). The command line turns any of them into
one line naming what and where (python-can's ``CanError`` is the model). Each class also keeps the built-in
base its callers already catch (``ValueError`` for a bad value, ``RuntimeError`` for a bad state), so
``except ValueError`` still works where it did. It lives in ``models/`` because that is the bottom of the
house: every layer may import it.
"""

from __future__ import annotations


class VslabError(Exception):
    """Base of every error vslab raises on purpose (a user's bad input, a device's fault, a damaged file)."""


class ModelError(VslabError):
    """The robot as mathematics: a bad description, an unreachable pose, an estimator used before fit."""


class NotFittedError(ModelError, ValueError, AttributeError):
    """An estimator used before ``fit`` (scikit-learn's meaning, and its bases: ``ValueError``,
    ``AttributeError``). The one "not fitted" error of every fitted thing in vslab."""
