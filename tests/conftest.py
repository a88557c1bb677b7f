"""Shared test set-up: headless rendering everywhere."""

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
