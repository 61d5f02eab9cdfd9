"""Suite-wide setup: headless GL before anything imports OpenGL, and hardware never touched."""

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
# UV atlases are cached on disk across commands (sim.assets.atlas_cache_dir); the suite keeps its
# cache inside the clone, never in the user's home.
os.environ.setdefault(
    "ADVOBJ_CACHE_DIR", os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".cache", "test")
)
