"""``python -m polins`` runs the command line."""

import sys

from polins.cli import main

sys.exit(main())
