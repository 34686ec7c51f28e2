"""``python -m ceemx`` runs the ``ceemx`` command."""

import sys

from .cli import main

sys.exit(main())
