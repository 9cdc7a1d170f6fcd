"""Mesh files (STL, PLY, OBJ, OFF, GLB/glTF) read through trimesh."""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from .fragment import FragmentError

MESH_SUFFIXES = {".stl", ".ply", ".obj", ".off", ".glb", ".gltf"}

# Formats trimesh reads as one mesh: loaded without force="mesh", which on a 6M-face PLY costs
# 0.8 GiB more at its peak (a scene is made and flattened again).
SINGLE_MESH_SUFFIXES = {".ply", ".stl", ".off"}
# After reading a mesh of more faces, trimesh's objects (reference cycles: a mesh and its
# visuals) are collected at once rather than at the next automatic collection: 0.8 GiB on 6M faces.
COLLECT_ABOVE = 200_000


def _read_meshes(p: Path, label: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """(vertices, faces) of each mesh of a file: one, or one per mesh of a GLB/glTF scene.

    Returns
    -------
    list of (vertices (V, 3) float64, faces (F, 3) int)
    """
    import gc

    import trimesh

    suffix = p.suffix.lower()
    scene = suffix in (".glb", ".gltf")
    force = {} if scene or suffix in SINGLE_MESH_SUFFIXES else {"force": "mesh"}
    try:
        with warnings.catch_warnings():  # e.g. an OBJ whose .mtl is missing: the geometry is what counts
            warnings.simplefilter("ignore")
            loaded = trimesh.load(str(p), process=False, **force)
            if isinstance(loaded, trimesh.Scene) and not scene:  # e.g. an STL of several solids: as force="mesh"
                loaded = loaded.to_mesh()
            meshes = loaded.dump() if isinstance(loaded, trimesh.Scene) else [loaded]
    except Exception as exc:
        raise FragmentError(f"{label}: unreadable {suffix[1:].upper()} file ({type(exc).__name__}: {exc})") from None
    out = [(np.asarray(m.vertices, np.float64), np.asarray(m.faces))
           for m in meshes if len(getattr(m, "vertices", ())) and len(getattr(m, "faces", ()))]
    faces = sum(len(f) for _, f in out)
    del loaded
    if faces > COLLECT_ABOVE:
        meshes.clear()
        gc.collect()
    if not out and not any(len(getattr(m, "vertices", ())) for m in meshes):
        raise FragmentError(f"{label}: unreadable or empty {suffix[1:].upper()} file (no vertices)")
    if not out:
        raise FragmentError(f"{label}: the mesh has no faces")
    return out


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
