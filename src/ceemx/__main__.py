"""``python -m ceemx`` runs the ``ceemx`` command (exit status 130 when interrupted)."""

import sys

from ceemx.cli import main

sys.exit(main())
