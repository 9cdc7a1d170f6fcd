"""LAS and LAZ lidar point clouds, read by laspy (LAZ through its lazrs backend)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .fragment import FragmentError

# LAS/LAZ lidar clouds, read by laspy (`read_las`; LAZ through its lazrs backend)
LIDAR_SUFFIXES = {".las", ".laz"}

# Extra dimensions of a LAS file read as normals, lower case (CloudCompare, PDAL and others)
LAS_NORMAL_NAMES = (("normalx", "normaly", "normalz"), ("normal_x", "normal_y", "normal_z"), ("nx", "ny", "nz"))


def read_las(path, label: str | None = None) -> tuple[np.ndarray, np.ndarray | None, list[str]]:
    """Read a LAS or LAZ point cloud with laspy.

    Parameters
    ----------
    path : path-like, a .las or .laz file (LAZ needs laspy's lazrs backend)
    label : str, optional
        Names the file in messages (default: the path).

    Returns
    -------
    points : (N, 3) float64
        x, y, z with the file's scales and offsets applied.
    normals : (N, 3) float64 or None
        From extra dimensions NormalX/NormalY/NormalZ, normal_x/... or nx/ny/nz (any case),
        made unit length; None when the file has none, or some are zero or not finite
        (a note says so).
    notes : list of str

    Raises
    ------
    FragmentError
        laspy (or for LAZ a decompression backend) is missing, or the file cannot be read.
    """
    p = Path(path)
    label = label or str(p)
    kind = p.suffix[1:].upper() or "LAS"
    try:
        import laspy
    except ImportError:
        raise FragmentError(f"{label}: {kind} point clouds need laspy (pip install laspy lazrs); "
                            "or convert it to .ply, .pcd, .xyz or .npy") from None
    if kind == "LAZ" and not laspy.LazBackend.detect_available():
        raise FragmentError(f"{label}: LAZ needs a decompression backend for laspy (pip install lazrs)")
    try:
        las = laspy.read(str(p))
        points = np.column_stack([np.asarray(las.x, np.float64), np.asarray(las.y, np.float64),
                                  np.asarray(las.z, np.float64)])
        extra = {n.lower(): n for n in las.point_format.extra_dimension_names}
        found = next((names for names in LAS_NORMAL_NAMES if all(n in extra for n in names)), None)
        normals = None if found is None else np.column_stack([np.asarray(las[extra[n]], np.float64) for n in found])
    except Exception as exc:  # laspy raises its own errors, and struct/ValueError/OSError on truncated files
        raise FragmentError(f"{label}: unreadable {kind} file ({type(exc).__name__}: {exc})") from None
    notes: list[str] = []
    if normals is not None:
        with np.errstate(invalid="ignore"):
            length = np.linalg.norm(normals, axis=1)
        if not (np.isfinite(length).all() and (length > 0).all()):
            notes.append(f"{label}: normals ({', '.join(extra[n] for n in found)}) hold zero, NaN or infinite "
                         "vectors; ignored")
            normals = None
        else:
            normals = normals / length[:, None]
    return points, normals, notes
