"""``python -m openfusion.services.semantic`` = ``openfusion service semantic``."""

import sys

from openfusion.services.semantic.service import DEFINITION

sys.exit(DEFINITION.main())
