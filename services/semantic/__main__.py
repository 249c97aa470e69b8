"""``python -m openfusion.services.semantic`` = ``openfusion service semantic``."""

import sys

from openfusion.app.cli import main

sys.exit(main(["service", "semantic", *sys.argv[1:]]))
