"""``python -m openfusion.eval``: the same as ``openfusion eval``."""

import sys

from openfusion.app.eval_cmd import main

sys.exit(main())
