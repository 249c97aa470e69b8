"""``python -m openfusion.services.geometry`` = ``openfusion service geometry``."""

import sys

from openfusion.services.geometry.service import DEFINITION

sys.exit(DEFINITION.main())
