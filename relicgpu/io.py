"""Loading fragments and writing outputs.

`load_fragment(path)` reads STL, PLY, OBJ, OFF or GLB meshes through trimesh
into a `Fragment`; point clouds go through `relicgpu.pointcloud` when that
stage is installed. Every fault a user can cause becomes a `FragmentError` that
names the file and the fault. Outputs are written atomically (a temporary file
beside the target, then a rename), never over an input.
"""
from __future__ import annotations

import json
import os
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

MESH_SUFFIXES = {".stl", ".ply", ".obj", ".off", ".glb", ".gltf"}
POINT_SUFFIXES = {".xyz", ".asc", ".txt", ".pcd", ".npy"}


class FragmentError(ValueError):
    """Bad input: the message names the file and the fault."""


@dataclass(frozen=True, eq=False)
class Fragment:
    """A scanned fragment: a triangle mesh with a name (the file stem)."""
    name: str
    vertices: np.ndarray  # (V,3) float64
    faces: np.ndarray  # (F,3) int32
    source: str | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def size(self) -> float:
        """The diagonal of the axis-aligned bounding box: the length scale of the fragment."""
        if len(self.vertices) == 0:
            return 0.0
        return float(np.linalg.norm(self.vertices.max(0) - self.vertices.min(0)))

    def transformed(self, matrix: np.ndarray) -> "Fragment":
        m = np.asarray(matrix, np.float64)
        v = self.vertices @ m[:3, :3].T + m[:3, 3]
        return Fragment(self.name, v, self.faces, self.source, self.notes)

    def to_trimesh(self):
        import trimesh
        return trimesh.Trimesh(self.vertices, self.faces, process=False)


def fragment_from_arrays(name: str, vertices, faces, source: str | None = None) -> Fragment:
    """Check and clean raw arrays into a Fragment (same rules as for files)."""
    label = source or name
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise FragmentError(f"{label}: vertices must be an (N, 3) array, got shape {v.shape}")
    if f.size == 0:
        raise FragmentError(f"{label}: the mesh has no faces")
    if f.ndim != 2 or f.shape[1] != 3:
        raise FragmentError(f"{label}: faces must be triangles, an (M, 3) array, got shape {f.shape}")
    if not np.isfinite(v).all():
        bad = int((~np.isfinite(v)).any(axis=1).sum())
        raise FragmentError(f"{label}: {bad} vertices have NaN or infinite coordinates")
    if f.min() < 0 or f.max() >= len(v):
        raise FragmentError(f"{label}: faces refer to vertices that do not exist (index {int(f.max())} of {len(v)})")
    f = f.astype(np.int64)
    notes: list[str] = []

    # Degenerate faces: a repeated vertex index or zero area.
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    area2 = np.linalg.norm(cross, axis=1)
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    degenerate = repeated | (area2 <= 1e-14 * max(1.0, float(np.abs(v).max())) ** 2)
    # Duplicate faces: the same vertex set, whatever the order.
    key = np.sort(f, axis=1)
    _, first = np.unique(key, axis=0, return_index=True)
    duplicate = np.ones(len(f), bool)
    duplicate[first] = False
    drop = degenerate | duplicate
    if drop.any():
        msg = f"{label}: removed {int(degenerate.sum())} degenerate and {int((duplicate & ~degenerate).sum())} duplicate faces"
        warnings.warn(msg, stacklevel=3)
        notes.append(msg)
        f = f[~drop]
    if len(f) == 0:
        raise FragmentError(f"{label}: the mesh has no faces left after removing degenerate ones")

    # Drop vertices no face uses, keep the order of the rest.
    used = np.zeros(len(v), bool)
    used[f.ravel()] = True
    remap = np.cumsum(used) - 1
    v, f = v[used], remap[f]

    n_bodies = count_bodies(v, f)
    if n_bodies > 1:
        raise FragmentError(f"{label}: the mesh has {n_bodies} separate bodies; a fragment must be one piece (split it first)")
    if not is_watertight(f):
        notes.append(f"{label}: the mesh is not watertight (open boundary); accepted, as scans often are")
    return Fragment(name, v, f.astype(np.int32), source, tuple(notes))


def count_bodies(vertices: np.ndarray, faces: np.ndarray) -> int:
    """Connected components of the faces, joining faces that share a vertex position."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    # Merge coincident vertices first: many formats (STL) store each triangle apart.
    _, inverse = np.unique(np.round(vertices, 12), axis=0, return_inverse=True)
    f = inverse.ravel()[faces]
    n = int(f.max()) + 1
    rows = np.repeat(np.arange(len(f)), 3)
    graph = coo_matrix((np.ones(len(rows)), (rows, f.ravel())), shape=(len(f), n))
    # faces x vertices incidence -> components over the bipartite graph
    m = len(f)
    from scipy.sparse import bmat
    big = bmat([[None, graph], [graph.T, None]])
    n_comp, labels = connected_components(big, directed=False)
    return len(np.unique(labels[:m]))


def is_watertight(faces: np.ndarray) -> bool:
    """Every undirected edge is shared by exactly two faces."""
    f = np.asarray(faces, np.int64)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool(np.all(counts == 2))


def load_fragment(path, name: str | None = None) -> Fragment:
    """Read a mesh (or a point cloud, triangulated) into a checked, cleaned Fragment."""
    p = Path(path)
    label = str(p)
    if not p.exists():
        raise FragmentError(f"{label}: no such file")
    if p.is_dir():
        raise FragmentError(f"{label}: is a directory, not a mesh file")
    suffix = p.suffix.lower()
    if suffix in POINT_SUFFIXES or (suffix == ".ply" and _ply_without_faces(p)):
        try:
            from . import pointcloud
        except ImportError as exc:  # the point-cloud stage is optional
            raise FragmentError(f"{label}: point clouds need relicgpu.pointcloud ({exc})") from exc
        return pointcloud.load_point_cloud_fragment(p, name=name)
    if suffix not in MESH_SUFFIXES:
        raise FragmentError(f"{label}: unknown format {suffix or '(no extension)'!r}; use STL, PLY, OBJ, OFF or GLB")
    import trimesh

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            loaded = trimesh.load(str(p), process=False, force="mesh")
    except Exception as exc:
        raise FragmentError(f"{label}: unreadable {suffix[1:].upper()} file ({type(exc).__name__}: {exc})") from None
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), np.float64)
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))))
    if len(vertices) == 0 and len(faces) == 0:
        raise FragmentError(f"{label}: unreadable or empty {suffix[1:].upper()} file (no vertices)")
    return fragment_from_arrays(name or p.stem, vertices, faces, source=label)


def _ply_without_faces(path: Path) -> bool:
    """True for a PLY whose header declares no faces (a point cloud)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return False
    if not head.startswith(b"ply"):
        return False
    header = head.split(b"end_header")[0].decode("ascii", "replace")
    for line in header.splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[0] == "element" and parts[1] == "face":
            return int(parts[2]) == 0
    return True


def load_directory(directory) -> list[Fragment]:
    """All fragment files of a directory (sorted by name)."""
    d = Path(directory)
    if not d.is_dir():
        raise FragmentError(f"{d}: not a directory")
    files = sorted(p for p in d.iterdir() if p.suffix.lower() in MESH_SUFFIXES | POINT_SUFFIXES)
    if not files:
        raise FragmentError(f"{d}: no fragment files (STL, PLY, OBJ, OFF, GLB, or point clouds) found")
    return [load_fragment(p) for p in files]


# --- atomic outputs --------------------------------------------------------

def atomic_write_bytes(path, data: bytes) -> None:
    """Write data to path via a temporary file in the same directory and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
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


def atomic_write_json(path, obj) -> None:
    atomic_write_bytes(path, (json.dumps(obj, indent=2, default=_json_default) + "\n").encode())


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def write_mesh(path, vertices, faces) -> None:
    """Write a mesh (format from the suffix) atomically."""
    import trimesh
    path = Path(path)
    data = trimesh.Trimesh(np.asarray(vertices), np.asarray(faces), process=False).export(file_type=path.suffix[1:].lower())
    atomic_write_bytes(path, data if isinstance(data, bytes) else data.encode())


def ensure_not_input(out_path, inputs) -> None:
    """Refuse to write an output over one of the inputs."""
    out = Path(out_path).resolve()
    for i in inputs:
        if Path(i).resolve() == out:
            raise FragmentError(f"{out}: refusing to overwrite an input file")
