"""Former home of the metrics (kept importable): see :mod:`stereorepro.measure.metrics`."""

from .measure.metrics import *  # noqa: F401,F403
from .measure.metrics import __all__  # noqa: F401
