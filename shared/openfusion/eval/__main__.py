"""``python -m openfusion.eval``: the same as ``openfusion eval``."""

import sys

from openfusion.app.cli import main

sys.exit(main(["eval", *sys.argv[1:]]))
