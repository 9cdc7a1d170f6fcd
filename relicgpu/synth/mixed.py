"""Objects whose pieces come at different resolutions: every other piece decimated in place.

Breaking Bad's pieces are cut from one mesh and share their break, yet one piece may hold 190
faces and its neighbour 15,000. `decimated` makes that case of any `SynthResult`: the pieces keep
their break within the tolerance, unlike the corpus's coarse scans made again at another
resolution (`bench_generalize.py --coarse-faces`: remeshes of their own, a low-resolution rescan).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..io.fragment import Fragment
from .corpus import _decimate, _manifold, object_size
from .truth import SynthResult


def decimated(result: SynthResult, faces: int, tolerance: float = 0.005, every: int = 2) -> SynthResult:
    """`result` with pieces 1, 1 + every, ... decimated towards `faces` faces (manifold3d's
    error-bounded edge collapse, within `tolerance` of the object size), each new face labelled
    as the nearest face of the piece before; poses and contacts unchanged.

    Parameters
    ----------
    result : SynthResult with `fracture_faces`
    faces : int, the faces a decimated piece is brought towards (its breaks' facets may keep more)
    tolerance : float, the largest distance a surface moves, as a share of the object size
    every : int, decimate one piece in this many
    """
    from scipy.spatial import cKDTree

    fragments, labels = list(result.fragments), list(result.fracture_faces)
    bound = tolerance * object_size(result)
    for k in range(1, len(fragments), every):
        old = fragments[k]
        mesh = _decimate(_manifold(old.vertices, old.faces), faces, bound).to_mesh64()
        v, f = np.array(mesh.vert_properties, np.float64)[:, :3], np.array(mesh.tri_verts, np.int64)
        _, nearest = cKDTree(old.vertices[old.faces].mean(1)).query(v[f].mean(1))
        fragments[k] = Fragment(old.name, v, f.astype(np.int32))
        labels[k] = np.asarray(result.fracture_faces[k])[nearest]
    return replace(result, fragments=fragments, fracture_faces=labels)
