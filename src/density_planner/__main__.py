"""``python -m density_planner``: same as the ``density-planner`` console script."""

import sys

from .cli import main

sys.exit(main())
