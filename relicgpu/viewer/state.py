"""What the viewer's routes share, kept on the app as `app.extensions["relicgpu"]`:
the workspace, the pipeline hooks, the caches of loaded meshes and prepared
fragments, the case scales, the compute slots and the job runner."""
from __future__ import annotations

import json
import os
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from ..io.fragment import FragmentError
from ..io.load import load_fragments
from .jobs import JobRunner
from .workspace import split_entries, Workspace

CACHE_FRAGMENTS = 128  # loaded meshes, and prepared fragments, kept in memory


class ApiError(Exception):
    """An API failure answered as {"error": message} with an HTTP status.

    Parameters
    ----------
    status : int
        The HTTP status (4xx or 5xx).
    message : str
        One line for the user.
    """

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status
        self.message = message


class LruCache:
    """A small LRU keyed by (path, mtime, size): a rewritten file is a new key.

    compute() runs once per key even when several requests ask at the same time.

    Parameters
    ----------
    limit : int
        The most values kept.
    """

    def __init__(self, limit: int) -> None:
        self._limit = limit
        self._data: OrderedDict = OrderedDict()
        self._lock = threading.Lock()
        self._key_locks: dict = {}

    def peek(self, key, default=None):
        """The value kept for key, else default (never computes)."""
        with self._lock:
            return self._data.get(key, default)

    def get(self, key, compute):
        """The value of key, from compute() on the first ask (one call per key at a time)."""
        with self._lock:
            if key in self._data:
                self._data.move_to_end(key)
                return self._data[key]
            key_lock = self._key_locks.setdefault(key, threading.Lock())
        with key_lock:
            with self._lock:
                if key in self._data:
                    return self._data[key]
            try:
                value = compute()
            except BaseException:
                with self._lock:
                    self._key_locks.pop(key, None)
                raise
            with self._lock:
                self._key_locks.pop(key, None)
                self._data[key] = value
                self._data.move_to_end(key)
                while len(self._data) > self._limit:
                    self._data.popitem(last=False)
            return value


def assembly_bodies(path: Path | None) -> dict[str, tuple[int, int]]:
    """file -> (fragments assembly.json lists from it, assembly.json's mtime in ns); empty
    where there is no readable assembly.json. Cheap: no mesh is read."""
    if path is None:
        return {}
    try:
        mtime = path.stat().st_mtime_ns
        items = json.loads(path.read_text(encoding="utf-8")).get("fragments")
    except (OSError, ValueError, AttributeError):
        return {}
    out: dict[str, tuple[int, int]] = {}
    for item in items if isinstance(items, list) else []:
        file = item.get("file") if isinstance(item, dict) else None
        if isinstance(file, str):
            out[file] = (out.get(file, (0, mtime))[0] + 1, mtime)
    return out


def file_key(path: Path) -> tuple:
    """(path, mtime in ns, size): the cache key of a file's contents."""
    st = path.stat()
    return (str(path), st.st_mtime_ns, st.st_size)


class ViewerState:
    """The state of one viewer app and the lookups its routes share.

    Parameters
    ----------
    workspace : Workspace
        The cases served.
    page_dir : Path
        The page's folder (index.html, the ES modules, node_modules/three).
    hooks : dict
        "prepare", "match_pair" and "assemble": the pipeline stages (see create_app).
    capabilities : dict
        "prepare", "match", "assemble": whether each stage can run here.
    """

    def __init__(self, workspace: Workspace, page_dir: Path, hooks: dict, capabilities: dict) -> None:
        self.ws = workspace
        self.page_dir = page_dir
        self.three_dir = page_dir / "node_modules" / "three"
        self.hooks = hooks
        self.capabilities = capabilities
        self.meshes = LruCache(CACHE_FRAGMENTS)
        self.prepared = LruCache(CACHE_FRAGMENTS)
        self._scales: dict = {}
        self._scales_lock = threading.Lock()
        self.compute_slots = threading.BoundedSemaphore(max(1, min(2, os.cpu_count() or 1)))
        self.jobs = JobRunner()

    def case_or_404(self, case_id):
        """The workspace's case of that id; ApiError 404 when there is none."""
        case = self.ws.case(case_id)
        if case is None:
            raise ApiError(404, f"unknown case {case_id!r}")
        return case

    def file_fragments(self, entry) -> list:
        """The fragments of an entry's file (io.load_fragments: one per body), loaded once."""
        def load():
            try:
                return load_fragments(entry.path, name=entry.name)[0]
            except FragmentError as exc:
                raise ApiError(422, str(exc).replace(str(self.ws.root) + os.sep, "")) from None
        return self.meshes.get(file_key(entry.path), load)

    def _body_names(self, entry):
        try:
            return [f.name for f in self.file_fragments(entry)]
        except ApiError:  # unreadable: the file's own entry stays, its mesh request says why
            return None

    def entries_of(self, case) -> dict:
        """One entry per fragment of a case: per body of each file (files are read once)."""
        return split_entries(self.ws.fragments(case), self._body_names)

    def entry_or_404(self, case, name):
        """The entry of fragment `name` in case; ApiError 404 when there is none."""
        entries = self.entries_of(case)
        if not isinstance(name, str) or name not in entries:
            raise ApiError(404, f"unknown fragment {name!r} in case {case.id!r}")
        return entries[name]

    def fragment_of(self, entry):
        """The loaded relicgpu Fragment of an entry (its body of its file)."""
        return self.file_fragments(entry)[entry.body]

    def fragment_count(self, case) -> tuple[int, bool]:
        """(fragments of a case, exact): its bodies, counted without reading a mesh (see
        relicgpu.viewer.app for /api/cases); exact is False where a file's bodies are unknown."""
        files = self.ws.fragments(case).values()
        listed = assembly_bodies(self.ws.assembly_file(case, "assembly.json"))
        count, exact = 0, True
        for e in files:
            key = file_key(e.path)
            loaded = self.meshes.peek(key)
            if loaded is not None:
                count += len(loaded)
            elif e.file in listed and listed[e.file][1] >= key[1]:
                count += listed[e.file][0]
            else:
                count, exact = count + 1, False
        return count, exact

    def case_scale(self, case) -> float:
        """The scale every fragment of a case is prepared at: the median fragment size."""
        files = list(self.ws.fragments(case).values())
        key = tuple(file_key(e.path) for e in files)  # stat only: no mesh reloads once known
        with self._scales_lock:
            if key in self._scales:
                return self._scales[key]
        sizes = []
        for e in files:
            try:
                sizes += [f.size for f in self.file_fragments(e)]
            except ApiError:
                continue
        scale = float(np.median(sizes)) if sizes else 1.0
        with self._scales_lock:
            if len(self._scales) > 256:
                self._scales.clear()
            self._scales[key] = scale
        return scale

    def prepared_of(self, case, entry):
        """The prepared fragment of an entry at its case's scale, prepared once."""
        if not self.capabilities["prepare"]:
            raise ApiError(503, "relicgpu.prepare is not available in this installation")
        frag = self.fragment_of(entry)
        scale = self.case_scale(case)

        def compute():
            with self.compute_slots:
                return self.hooks["prepare"](frag, scale)
        return self.prepared.get(file_key(entry.path) + (entry.body, scale), compute)
