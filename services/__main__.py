"""``python -m services ARGS`` runs the ``posegrid`` command line (how the launcher starts its children)."""

import sys

from services.cli import main

sys.exit(main())
