"""``python -m edgecal`` runs the command line."""

import sys

from edgecal.cli import main

sys.exit(main())
