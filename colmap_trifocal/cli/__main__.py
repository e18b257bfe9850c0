"""``python -m colmap_trifocal.cli ARGS``: the same as the ``colmap-trifocal`` script."""

import sys

from .app import main

sys.exit(main())
