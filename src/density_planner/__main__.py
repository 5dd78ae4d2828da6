"""``python -m density_planner``: same as the ``density-planner`` console script."""

from .cli import console

console()
