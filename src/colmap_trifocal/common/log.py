"""The package logger (quiet by default: a NullHandler, level set by the CLI)."""

import logging

logger = logging.getLogger("colmap_trifocal")
logger.addHandler(logging.NullHandler())
