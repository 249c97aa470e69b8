"""``python -m openfusion.services.geometry`` = ``openfusion service geometry``."""

import sys

from openfusion.app.cli import main

sys.exit(main(["service", "geometry", *sys.argv[1:]]))
