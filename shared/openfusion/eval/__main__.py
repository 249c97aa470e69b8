"""``python -m openfusion.eval``: the same as ``openfusion eval``."""

import sys

from openfusion.eval.cli import main

sys.exit(main())
