"""``python -m openfusion.services.bridge`` = ``openfusion service bridge``."""

import sys

from openfusion.services.bridge.service import DEFINITION

sys.exit(DEFINITION.main())
