"""Former home of the paper's experiment (kept importable): see :mod:`stereorepro.workflows.experiment` and
:mod:`stereorepro.cli.experiment`."""

from .cli.experiment import add_arguments, config_from_args, register  # noqa: F401
from .workflows.experiment import (REFERENCE_OFFSET, SCHEMES, THRESHOLD_ROWS, ExperimentConfig,  # noqa: F401
                                 RenderCache, cost_markdown, run_experiment, tables_markdown)

__all__ = ["ExperimentConfig", "run_experiment", "REFERENCE_OFFSET", "register", "SCHEMES"]
