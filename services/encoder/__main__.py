"""``python -m openfusion.services.encoder`` = ``openfusion service encoder``."""

import sys

from openfusion.app.cli import main

sys.exit(main(["service", "encoder", *sys.argv[1:]]))
