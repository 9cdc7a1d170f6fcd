"""Writing outputs atomically (a temporary file beside the target, then a rename), never over an
input: bytes, JSON, binary STL and other meshes; and the terminal's grouped notes."""
from __future__ import annotations

import contextlib
import json
import os
import re
import tempfile
from pathlib import Path

import numpy as np

from .fragment import FragmentError

def grouped_lines(prefix: str, messages: list[str], shown: int = 3) -> list[str]:
    """Terminal lines for messages ``"<file>: <what>"``: one line per kind of `what` (its
    numbers and parentheses aside), the first message in full and a count of the others like it.

    ["a.ply: not watertight", "b.ply: not watertight"] -> ["note: a.ply: not watertight
    (and 1 more like it: b.ply)"]
    """
    kinds: dict[str, list[str]] = {}
    for m in messages:
        what = m.split(": ", 1)[-1]
        kind = re.sub(r"\d+(?:\.\d+)?(?:e[-+]?\d+)?", "#", re.sub(r"\([^)]*\)", "()", what))
        kinds.setdefault(kind, []).append(m)
    lines = []
    for group in kinds.values():
        line = f"{prefix}: {group[0]}"
        if len(group) > 1:
            others = [m.split(": ", 1)[0] for m in group[1:]]
            listed = ", ".join(others[:shown]) + (", ..." if len(others) > shown else "")
            line += f" (and {len(others)} more like it: {listed}; all listed in the JSON output)"
        lines.append(line)
    return lines


# --- atomic outputs --------------------------------------------------------

@contextlib.contextmanager
def atomic_open(path):
    """A binary file to write `path` through: a temporary file in the same directory, renamed
    over `path` when the block ends without an exception (removed otherwise)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w+b") as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        # mkstemp makes the file private (0600); give it the mode a plain open() would
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def atomic_write_bytes(path, data: bytes) -> None:
    """Write data to path via a temporary file in the same directory and a rename."""
    with atomic_open(path) as fh:
        fh.write(data)


def atomic_write_json(path, obj) -> None:
    atomic_write_bytes(path, (json.dumps(obj, indent=2, default=_json_default) + "\n").encode())


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


# A binary STL facet: unit normal, three corners, a zero attribute count (50 bytes).
STL_FACET = np.dtype([("normal", "<f4", (3,)), ("corners", "<f4", (3, 3)), ("attr", "<u2")])
STL_CHUNK = 1 << 19  # facets converted at a time (about 40 MB of temporaries)


def write_stl(fh, parts, on_faces=None) -> int:
    """Write meshes into one binary STL, a chunk of faces at a time (nothing the size of the
    whole file is held in memory); the facet count is filled in at the end (`fh` must seek).

    Parameters
    ----------
    fh : binary file open for writing at its start
    parts : iterable of (vertices (V, 3) float32 or float64, faces (F, 3) int)
        Consumed one at a time: a generator can free each mesh once written.
    on_faces : callable(int), optional
        Told how many faces each chunk wrote (a progress bar).

    Returns
    -------
    int, the facets written
    """
    fh.write(b"relicgpu binary STL".ljust(80, b" "))
    fh.write(np.uint32(0).tobytes())
    total = 0
    for vertices, faces in parts:
        for start in range(0, len(faces), STL_CHUNK):
            tri = np.asarray(vertices[np.asarray(faces[start:start + STL_CHUNK], np.int64)], np.float64)  # (c, 3, 3)
            normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            length = np.linalg.norm(normal, axis=1, keepdims=True)
            facets = np.zeros(len(tri), STL_FACET)
            facets["normal"] = np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)
            facets["corners"] = tri
            fh.write(facets.tobytes())
            total += len(tri)
            if on_faces is not None:
                on_faces(len(tri))
    end = fh.tell()
    fh.seek(80)
    fh.write(np.uint32(total).tobytes())
    fh.seek(end)
    return total


def write_mesh(path, vertices, faces) -> None:
    """Write a mesh (format from the suffix) atomically; STL through `write_stl`."""
    import trimesh
    path = Path(path)
    if path.suffix.lower() == ".stl":
        with atomic_open(path) as fh:
            write_stl(fh, [(vertices, faces)])
        return
    data = trimesh.Trimesh(np.asarray(vertices), np.asarray(faces), process=False).export(file_type=path.suffix[1:].lower())
    atomic_write_bytes(path, data if isinstance(data, bytes) else data.encode())


def ensure_not_input(out_path, inputs) -> None:
    """Refuse to write an output over one of the inputs."""
    out = Path(out_path).resolve()
    for i in inputs:
        if Path(i).resolve() == out:
            raise FragmentError(f"{out}: refusing to overwrite an input file")
