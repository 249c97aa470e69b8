"""``python -m openfusion.services.query`` = ``openfusion service query``."""

import sys

from openfusion.app.cli import main

sys.exit(main(["service", "query", *sys.argv[1:]]))
