"""``python -m openfusion.services.bridge`` = ``openfusion service bridge``."""

import sys

from openfusion.app.cli import main

sys.exit(main(["service", "bridge", *sys.argv[1:]]))
