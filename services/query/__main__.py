"""``python -m openfusion.services.query`` = ``openfusion service query``."""

import sys

from openfusion.services.query.service import DEFINITION

sys.exit(DEFINITION.main())
