"""``python -m procam.addon.cli …``: the ``procam`` command, for a checkout that is on the path but not installed."""

import sys

from .app import main

sys.exit(main())
