"""Synthetic scenes with known K (cube, motions, synthetic COLMAP databases) and the demo.

Takes intrinsics and a motion, gives DatabaseContents or a database file plus ground truth.
Its public names (``__all__``, what the notebooks use): :func:`make_demo_database` (the
demo's database and its true camera), :func:`planar_orbit` (a motion that hides fy) and
:func:`scene_contents` (a scene's matches, as a database's snapshot).
"""

from .database import scene_contents
from .demo import make_demo_database
from .motions import planar_orbit

__all__ = ["make_demo_database", "planar_orbit", "scene_contents"]
