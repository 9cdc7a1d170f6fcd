"""The browser viewer: a Flask app (`relicgpu.viewer.app.create_app`) serving the
three.js page in the repository's `viewer/` folder and a small JSON API."""
from __future__ import annotations

__all__ = ["create_app", "serve"]


def __getattr__(name):
    # Flask loads only when the viewer is used.
    if name in __all__:
        from . import app
        return getattr(app, name)
    raise AttributeError(f"module 'relicgpu.viewer' has no attribute {name!r}")
