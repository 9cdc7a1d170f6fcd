"""Loading fragments: `load_fragment(path)` reads STL, PLY, OBJ, OFF or GLB meshes through
trimesh (`relicgpu.io.meshes`) into a `Fragment`; point clouds (.xyz, .pcd, .ply, .npy, and
.las/.laz through laspy) are read by `relicgpu.io.clouds` and triangulated by
`relicgpu.cloud.triangulate`. A batch of files (`read_batch`) keeps every file or body left out,
with why."""
from __future__ import annotations

import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

from ..cloud.triangulate import load_point_cloud_fragment
from ..progress import progress_bar
from .fragment import _checked_arrays, _clean_body, _largest_of, Fragment, FragmentError, split_bodies, THIN_ABOVE
from .clouds import POINT_SUFFIXES
from .files import grouped_lines
from .meshes import _ply_without_faces, _read_meshes, MESH_SUFFIXES

FRAGMENT_SUFFIXES = MESH_SUFFIXES | POINT_SUFFIXES


# read_batch shows a bar in bytes when its files hold more than this (a few seconds' reading)
READ_BAR_ABOVE = 50 * 2 ** 20


def load_fragment(path, name: str | None = None) -> Fragment:
    """Read a mesh (or a point cloud, triangulated) into a checked, cleaned Fragment.

    A file of several bodies (or a scene of several meshes) gives its largest body; its
    notes say so. `load_fragments` gives every body.
    """
    frags, skipped, notes = load_fragments(path, name)
    return _largest_of(frags, skipped, notes, str(path))


def load_fragments(path, name: str | None = None, thin_above: int | None = THIN_ABOVE, progress: bool = True,
                   ) -> tuple[list[Fragment], list[dict], list[str]]:
    """Read one file into a Fragment per body (or per mesh of a scene), crumbs dropped.

    Parameters
    ----------
    path : path-like
        A mesh (STL, PLY, OBJ, OFF, GLB/glTF) or point-cloud file.
    name : str, optional
        The id of the fragment (default: the file stem); bodies are ``name#k``.
    thin_above : int or None
        Bodies of more faces are thinned to about THIN_TO faces (`thin`; the fragment's
        ``thinned_from`` and a note say so); None keeps every face.
    progress : bool
        Report thinning on stderr (`thin`); False for ``--quiet``.

    Returns
    -------
    fragments, skipped, notes
        As `fragments_from_arrays`.

    Raises
    ------
    FragmentError
        The file cannot be read; the message names the file and the fault.
    """
    p = Path(path)
    label = str(p)
    name = name or p.stem
    if not p.exists():
        raise FragmentError(f"{label}: no such file")
    if p.is_dir():
        raise FragmentError(f"{label}: is a directory, not a mesh file")
    suffix = p.suffix.lower()
    if suffix in POINT_SUFFIXES or (suffix == ".ply" and _ply_without_faces(p)):
        return [load_point_cloud_fragment(p, name=name)], [], []
    if suffix not in MESH_SUFFIXES:
        raise FragmentError(f"{label}: unknown format {suffix or '(no extension)'!r}; use STL, PLY, OBJ, OFF or GLB")
    parts = [_checked_arrays(label, v, f) for v, f in _read_meshes(p, label)]
    return split_bodies(name, label, label, parts, thin_above, progress)


def load_original(fragment: Fragment) -> Fragment:
    """A fragment as its file holds it: read again where it was thinned at load (same
    cleaning, no thinning, nothing on stderr), else the fragment itself (also when the file
    can no longer be read). A file that is that one body is not split into bodies again.
    Its notes are not made again (they were said at load): no watertightness test.
    """
    if not fragment.thinned_from or not fragment.source:
        return fragment
    label = fragment.source
    try:
        parts = [_checked_arrays(label, v, f) for v, f in _read_meshes(Path(label), label)]
        if len(parts) == 1 and len(parts[0][1]) == fragment.thinned_from:
            (v, f), = parts
            del parts
            return _clean_body(fragment.name, v, f, label, fragment.source, describe=False)
        name = fragment.name
        for base in [name] + ([name.rsplit("#", 1)[0]] if "#" in name else []):
            found = [f for f in split_bodies(base, label, label, parts, None, False, describe=False)[0]
                     if f.name == name]
            if found:
                return found[0]
    except FragmentError:
        pass
    return fragment


# --- a batch of files -------------------------------------------------------

@dataclass
class Batch:
    """Fragments read from many files, and every file or body left out, with why.

    ``skipped`` holds ``{"file", "reason"}`` per unreadable file and ``{"file", "name",
    "reason"}`` per crumb; ``notes`` the other decisions (files split into several
    fragments, degenerate faces removed, open meshes accepted). Both go into assembly.json
    and groups.json, one line each on the terminal.
    """
    fragments: list[Fragment]
    skipped: list[dict] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    seconds: float = 0.0  # time taken to read it

    def messages(self) -> list[str]:
        """The terminal lines: one per kind of decision (see `grouped_lines`; the JSON lists each)."""
        return (grouped_lines("skipped", [s["reason"] for s in self.skipped])
                + grouped_lines("note", self.notes))

    def require(self, n: int = 2) -> None:
        """Raise FragmentError when fewer than n fragments could be read."""
        if len(self.fragments) < n:
            unread = [s for s in self.skipped if "name" not in s]
            raise FragmentError(f"only {len(self.fragments)} fragment(s) could be read, {n} are needed"
                                + (f" ({len(unread)} file(s) skipped, first: {unread[0]['reason']})" if unread else ""))


def fragment_ids(files) -> list[str]:
    """The id of each file of a batch: its stem where no other file has that stem, else its
    name with the extension (``a.ply`` and ``a.obj``), else the path as given."""
    names = [Path(f).name for f in files]
    stems = [Path(f).stem for f in files]
    return [s if stems.count(s) == 1 else n if names.count(n) == 1 else str(f)
            for f, n, s in zip(files, names, stems)]


def fragment_files(directory) -> list[Path]:
    """The fragment files of a directory, sorted by name (FragmentError when there are none)."""
    d = Path(directory)
    if not d.is_dir():
        raise FragmentError(f"{d}: not a directory")
    files = sorted(p for p in d.iterdir() if p.is_file() and p.suffix.lower() in FRAGMENT_SUFFIXES)
    if not files:
        raise FragmentError(f"{d}: no fragment files (STL, PLY, OBJ, OFF, GLB, or point clouds) found")
    return files


def read_batch(fragments_or_dir, progress: bool = True) -> Batch:
    """Read a directory, or a list of files and Fragments; a file that cannot be read is skipped.

    Files are named by `fragment_ids`; Fragments given keep their names. `progress`: report
    the thinning of big meshes on stderr (`thin`); False for ``--quiet``.
    """
    if isinstance(fragments_or_dir, Batch):
        return fragments_or_dir
    if isinstance(fragments_or_dir, (str, os.PathLike)):
        items: list = fragment_files(fragments_or_dir)
    else:
        items = list(fragments_or_dir)
    t0 = time.perf_counter()
    paths = [Path(x) for x in items if not isinstance(x, Fragment)]
    ids = iter(fragment_ids(paths))
    batch = Batch([])
    # a bar in bytes read (a 5M-face mesh takes seconds to read and split before it is thinned)
    sizes = [0 if isinstance(x, Fragment) or not Path(x).is_file() else Path(x).stat().st_size for x in items]
    with progress_bar(sum(sizes), "reading", progress and sum(sizes) > READ_BAR_ABOVE, unit="B") as bar:
        for item, size in zip(items, sizes):
            if isinstance(item, Fragment):
                batch.fragments.append(item)
                continue
            p = Path(item)
            bar.set_postfix_str(p.name)
            try:
                with warnings.catch_warnings():  # what cleaning warns of is in the fragments' notes
                    warnings.simplefilter("ignore")
                    frags, skipped, notes = load_fragments(p, next(ids), progress=progress)
            except FragmentError as exc:
                batch.skipped.append({"file": p.name, "reason": str(exc)})
                continue
            finally:
                bar.update(size)
            batch.fragments += frags
            batch.skipped += skipped
            batch.notes += notes + [n for f in frags for n in f.notes]
    batch.seconds = time.perf_counter() - t0
    return batch


def load_directory(directory) -> list[Fragment]:
    """All fragments of a directory's files (sorted by name); see `read_batch` for what is skipped."""
    return read_batch(directory).fragments
