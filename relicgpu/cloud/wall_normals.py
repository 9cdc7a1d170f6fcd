"""Normals of a thin wall's cloud scanned without them: each face's own, and the break strip's.

A vessel's wall sampled at 2,500 points a piece is about two point spacings thick, so the plane
fitted to a point's nearest neighbours spans both faces. `estimate_normals` (12 nearest, turned
outward by visibility) leaves the skin's normals 27-37 degrees off, and the break strip between
the faces is read as neither skin nor break (docs/benchmarks.md, "Vessels as clouds without
normals"). Here, for each point:

- the wall's normal is the plane of its `SHEET` nearest (both faces), then averaged over those
  neighbours that lie inside the sheet rather than at its edge (their in-plane offset from their
  neighbours' centroid under `INNER` of their reach), turned to the side of the wall the point
  lies on (its offset from its neighbours' centroid along that normal);
- a point at the sheet's edge (in-plane offset over `EDGE`) whose `BETWEEN` nearest hold at least
  `BETWEEN_MIN` points more than `BETWEEN_OFFSET` spacings to each side along the wall's normal
  lies between the two faces: it is the break strip, and takes the in-plane outward direction.

On vessel-clean pairs without normals these normals, matched as if scanned, found fits where the
usual estimate found none (docs/benchmarks.md, "A thin wall's normals asked last"); on thick pieces
they find nothing. So `pair.pipeline.match_pair` asks them last, for two clouds without normals
that nothing else matched (`Params.wall_normals`), and refuses such a fit where it carries one
piece's axis of revolution off the other's (`revolution.axes_meet`) or lays a sherd upside down
(`revolution.profiles_agree`).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

SHEET = 32
INNER = 0.2
EDGE = 0.25
BETWEEN = 16
BETWEEN_MIN = 2
BETWEEN_OFFSET = 0.4


def wall_normals(points: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals of a thin wall's (N, 3) points (see the module docstring)."""
    p = np.asarray(points, np.float64)
    n = len(p)
    k = min(SHEET, n)
    dist, idx = cKDTree(p).query(p, k=k)
    q = p[idx]
    centre = q.mean(axis=1)
    d = q - centre[:, None]
    sheet = np.linalg.eigh(np.einsum("nki,nkj->nij", d, d) / k)[1][:, :, 0]
    off = p - centre
    along = np.einsum("ij,ij->i", off, sheet)
    inplane = off - along[:, None] * sheet
    reach = np.maximum(dist[:, -1], 1e-300)
    edge = np.linalg.norm(inplane, axis=1) / reach
    # the wall's normal over the neighbours inside the sheet (signs made to agree with the point's)
    inner = (edge < INNER)[idx] & (idx != np.arange(n)[:, None])
    signs = np.sign(np.einsum("nkd,nd->nk", sheet[idx], sheet))[..., None]
    wall = (sheet[idx] * signs * inner[..., None]).sum(axis=1)
    length = np.linalg.norm(wall, axis=1)
    wall = np.where(length[:, None] > 0, wall / np.maximum(length, 1e-300)[:, None], sheet)
    normals = wall * np.where(along < 0, -1.0, 1.0)[:, None]
    strip = (edge > EDGE) & (_between(p, dist, idx, wall) >= BETWEEN_MIN)
    outward = inplane - np.einsum("ij,ij->i", inplane, wall)[:, None] * wall
    size = np.linalg.norm(outward, axis=1)
    strip &= size > 0
    normals[strip] = outward[strip] / size[strip, None]
    return normals


def _between(points: np.ndarray, dist: np.ndarray, idx: np.ndarray, wall: np.ndarray) -> np.ndarray:
    """(N,) how many of each point's `BETWEEN` nearest lie more than `BETWEEN_OFFSET` spacings to
    its one side along the (N, 3) wall normals, counted on the side that holds fewer. `dist`, `idx`:
    (N, K) each point's K >= `BETWEEN` nearest (itself first), ascending, as cKDTree gives them."""
    dist, idx = dist[:, :BETWEEN], idx[:, :BETWEEN]
    nearest = dist[:, 1] if dist.shape[1] > 1 else dist[:, 0]
    spacing = float(np.median(nearest[nearest > 0])) if np.any(nearest > 0) else 0.0
    offset = np.einsum("nkd,nd->nk", points[idx] - points[:, None], wall)
    bar = BETWEEN_OFFSET * spacing
    return np.minimum((offset > bar).sum(axis=1), (offset < -bar).sum(axis=1))
