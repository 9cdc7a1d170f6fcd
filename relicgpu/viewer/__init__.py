"""The browser viewer: a Flask app (`relicgpu.viewer.app.create_app`) serving the
three.js page (the repository's `viewer/` folder, or the copy a wheel carries) and a
small JSON API. app: the factory, its guards and serving; routes: the Blueprint;
state: what the routes share; serialize: the JSON; hooks: the pipeline stages;
workspace: cases on disk; jobs: the background assembly."""
from __future__ import annotations

from .app import create_app, make_server, serve_in_thread

__all__ = ["create_app", "make_server", "serve_in_thread"]
