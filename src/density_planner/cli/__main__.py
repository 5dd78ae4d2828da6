"""``python -m density_planner.cli``: same as the ``density-planner`` console script."""

import sys

from . import main

sys.exit(main())
