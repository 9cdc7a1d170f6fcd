"""The assembly's cache: a file per prepared fragment, one for the screen and one per matched
pair, named by a hash of the fragment contents, the parameters, the scale, the backend and the
source of the pipeline stages (`code_fingerprint`), so that a result is reused only where it
would be computed again identically; written atomically as each job finishes."""
from __future__ import annotations

import hashlib
import json
import pickle
from pathlib import Path

import numpy as np

from ..io.files import atomic_write_bytes, atomic_write_json
from ..io.fragment import Fragment
from ..params import Params
from ..pair.prepare import received, shipped


CACHE_VERSION = 1


# --- hashing and the cache ---------------------------------------------------

# The sources a cached match depends on (globs under relicgpu/): the pair stages, the parameters,
# this module and the backends.
_STAGE_MODULES = ("pair/*", "topology", "cloud/points", "params", "heap/assembly", "heap/cache", "heap/screen", "heap/forest", "heap/grow",
                  "heap/describe", "heap/grouping",
                  "backends/__init__", "backends/_prep", "backends/numpy",
                  "backends/warp", "backends/opencl")


def fragment_hash(fragment: Fragment) -> str:
    """Content hash of a fragment's geometry (the cleaned arrays a file loads into)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(fragment.vertices, np.float64).tobytes())
    h.update(np.ascontiguousarray(fragment.faces, np.int64).tobytes())
    return h.hexdigest()[:32]


def code_fingerprint(params: Params) -> str:
    """Hash of the source of the pipeline stages and of the fusion weights: a cached result
    is reused only when the code that made it is the code that would make it again."""
    h = hashlib.sha256()
    base = Path(__file__).parents[1]
    for mod in _STAGE_MODULES:
        paths = sorted(base.glob(f"{mod}.py"))
        for p in paths:
            h.update(p.read_bytes())
        if not paths:
            h.update(b"-")
    weights = Path(params.fusion_weights) if params.fusion_weights else base / "data" / "fusion_default.npz"
    h.update(weights.read_bytes() if weights.exists() else b"hand-weighted")
    return h.hexdigest()[:16]


class Cache:
    """Results on disk under `root`, named by content keys; None root = no cache."""

    def __init__(self, root, params: Params, scale: float, backend_name: str):
        self.root = Path(root) if root else None
        ident = {"cache": CACHE_VERSION, "code": code_fingerprint(params), "params": params.to_dict(),
                 "scale": repr(float(scale)), "backend": backend_name}
        self.salt = hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()[:16]
        self.hits = 0
        self.writes = 0

    def _key(self, *parts: str) -> str:
        return hashlib.sha256("|".join((self.salt,) + parts).encode()).hexdigest()[:32]

    def _path(self, kind: str, key: str, suffix: str) -> Path | None:
        return None if self.root is None else self.root / kind / f"{key}{suffix}"

    def get_prepared(self, fragment: Fragment, h: str):
        path = self._path("prepared", self._key("prepared", h), ".pkl")
        if path is None or not path.exists():
            return None
        try:
            with open(path, "rb") as fh:
                prepared = pickle.load(fh)
            prepared = received(prepared, fragment)
        except Exception:  # an unreadable or stale file: compute again
            return None
        self.hits += 1
        return prepared

    def put_prepared(self, h: str, prepared, fragment: Fragment) -> None:
        path = self._path("prepared", self._key("prepared", h), ".pkl")
        if path is not None:
            # the fragment itself is not stored: it is what the key was made from
            atomic_write_bytes(path, pickle.dumps(shipped(prepared, fragment), protocol=5))
            self.writes += 1

    def get_pair(self, ha: str, hb: str) -> dict | None:
        path = self._path("pairs", self._key("pair", ha, hb), ".json")
        if path is None or not path.exists():
            return None
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError):
            return None
        self.hits += 1
        return doc

    def put_pair(self, ha: str, hb: str, doc: dict) -> None:
        path = self._path("pairs", self._key("pair", ha, hb), ".json")
        if path is not None:
            atomic_write_json(path, doc)
            self.writes += 1

    def get_array(self, name: str, *parts: str) -> np.ndarray | None:
        path = self._path("screen", self._key(name, *parts), ".npy")
        if path is None or not path.exists():
            return None
        try:
            arr = np.load(path, allow_pickle=False)
        except (OSError, ValueError):
            return None
        self.hits += 1
        return arr

    def put_array(self, name: str, arr: np.ndarray, *parts: str) -> None:
        path = self._path("screen", self._key(name, *parts), ".npy")
        if path is not None:
            import io as _io
            buf = _io.BytesIO()
            np.save(buf, arr, allow_pickle=False)
            atomic_write_bytes(path, buf.getvalue())
            self.writes += 1
