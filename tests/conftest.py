"""Suite-wide setup: headless GL before anything imports OpenGL, and hardware never touched."""

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
