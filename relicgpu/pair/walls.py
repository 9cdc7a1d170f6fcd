"""Thin walls (step 4 of relicgpu.pair.segment_cues): the wall's ends where a rescan rounded
them, the lips among them, the wall's thickness and the shape of a band (`band_shape`)."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..backends.numpy import query_threads
from ..topology import Topology, components, ring_average, weighted_quantile

# Wall ends (`wall_end_labels`, dense thin walls): chosen on corpus vessel-noisy and vessel-clean
# (seeds 0-3), voronoi-* and the Blender sets held out. Face-level recall / precision of "end faces
# less lips" on vessel-noisy: 0.885 / 0.809 (the crease regions: 0.61 / 0.59); WALL_END_ALIGN 0.8:
# 0.856 / 0.825, 0.85: 0.901 / 0.796, 0.9: 0.942 / 0.744 (the skin faces it adds lie within a wall
# of the break: its labels' own blur)
WALL_END_MIN_FACES = 1000  # meshes with fewer faces (coarse) keep the crease regions alone
WALL_END_RADIUS = 5.0  # the wall's axis is taken over faces within this many walls ...
WALL_END_NEIGHBOURS = 64  # ... at most this many
WALL_END_ALIGN = 0.83  # a face is on the wall's end where |cos| between its normal and the wall's axis is below this
LIP_CORE_ALIGN = 0.8  # lips are found among the faces below this (a wider set breaks their planar runs) ...
LIP_GROW_RINGS = 5  # ... and grown this many edge steps through the wall's ends (their rounded rims)
WALL_END_SOFTNESS = 0.05  # width of the logistic step on that |cos|
END_FLAT_RADIUS = 4.0  # an end face is locally planar when the end faces within this many walls ...
END_FLAT_WALLS = 0.15  # ... lie within this many walls (RMS) of one plane; runs of such faces are lips when
END_LIP_LENGTH_WALLS = 15.0  # ... longer than this many walls (noisy lips 20-34, breaks' planar runs up to 16.5) ...
END_LIP_BEND_WALLS = 2.5  # ... curved by more than this many walls (lips 4-16, breaks up to 2.3) ...
END_LIP_FLAT_WALLS = 0.1  # ... and within this many walls of one plane (noisy lips 0.02-0.1)
WALL_END_COVERED = 0.72  # the crease regions are kept where their fracture covers this share of the ends


def wall_end_alignment(centers: np.ndarray, normals: np.ndarray, areas: np.ndarray, wall: float) -> np.ndarray:
    """(F,) |cos| between each face's normal and the wall's axis around it: the dominant direction
    (principal eigenvector of the area-weighted sum of n n^T) of the normals of the faces within
    `WALL_END_RADIUS` walls (at most `WALL_END_NEIGHBOURS`). On a thin wall both skins' normals lie
    along that axis (|cos| near 1); the wall's end, a lip or a break, turns across it (near 0).
    `wall` is in object units."""
    k = min(WALL_END_NEIGHBOURS, len(centers))
    dist, near = cKDTree(centers).query(centers, k=k, distance_upper_bound=WALL_END_RADIUS * wall)
    ok = np.isfinite(dist)
    near = np.where(ok, near, np.arange(len(centers))[:, None])
    w = np.where(ok, areas[near], 0.0)
    nn = normals[near]  # (F, k, 3)
    m = np.einsum("fk,fki,fkj->fij", w, nn, nn)
    _, vec = np.linalg.eigh(m)
    return np.abs(np.einsum("fd,fd->f", normals, vec[:, :, 2]))


def end_lips(centers: np.ndarray, areas: np.ndarray, topo: Topology, end: np.ndarray, wall: float) -> np.ndarray:
    """(F,) bool, the end faces that belong to a lip: runs (edge-connected) of end faces that are
    locally planar (`END_FLAT_*`) and, as a whole, long, curved within their plane and flat
    (`END_LIP_*`, `band_shape`). `wall` is in object units."""
    lip = np.zeros(len(centers), bool)
    idx = np.flatnonzero(end)
    if len(idx) < 3:
        return lip
    c, a = centers[idx], areas[idx]
    k = min(32, len(idx))
    dist, near = cKDTree(c).query(c, k=k, distance_upper_bound=END_FLAT_RADIUS * wall)
    ok = np.isfinite(dist)
    near = np.where(ok, near, np.arange(len(idx))[:, None])
    w = np.where(ok, a[near], 0.0)
    w = w / np.maximum(w.sum(1, keepdims=True), 1e-300)
    d = c[near] - np.einsum("fk,fkd->fd", w, c[near])[:, None]
    cov = np.einsum("fk,fki,fkj->fij", w, d, d)
    planar = np.zeros(len(centers), bool)
    planar[idx] = np.sqrt(np.maximum(np.linalg.eigvalsh(cov)[:, 0], 0)) < END_FLAT_WALLS * wall
    e0, e1 = topo.edge_faces[:, 0], topo.edge_faces[:, 1]
    run = components(len(centers), topo.edge_faces[planar[e0] & planar[e1]])
    shape = band_shape(centers, areas, run) / max(wall, 1e-300)
    lip_run = ((shape[:, 0] > END_LIP_LENGTH_WALLS) & (shape[:, 1] > END_LIP_BEND_WALLS)
               & (shape[:, 2] < END_LIP_FLAT_WALLS))
    return planar & lip_run[run]


def wall_end_labels(centers: np.ndarray, normals: np.ndarray, areas: np.ndarray, topo: Topology, region: np.ndarray,
                    prob: np.ndarray, wall: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """Fracture on a dense thin wall: the crease regions' where their fracture covers most of the
    wall's ends (`WALL_END_COVERED` of the area of the ends less lips), less regions mostly of lip
    faces (a lip rounded a little, its rims too soft for `LIP_*`), else the wall's ends
    (`wall_end_alignment`) less its lips (`end_lips`).

    A rescan rounds the wall's end over a face or two (corpus vessel-noisy: edges 0.7-1.4 walls
    long), so no crease bounds the band and the crease regions merged it into the skin (they
    covered 0.46-0.69 of the ends there, 0.75-0.96 on vessel-clean but for one piece, 0.38); the
    turn of the normals across the wall finds it whatever the creases. Where sharp creases bound
    the band the crease regions are better: they also find a cut met at a slant, whose normal
    stays within `WALL_END_ALIGN` of the wall's axis.

    Parameters
    ----------
    centers, normals, areas : (F, 3), (F, 3), (F,) face centroids, unit normals, areas
    topo : the mesh's `Topology`
    region : (F,) crease region per face; prob : (R,) their likelihood (`region_fracture_prob`)
    wall : the wall's thickness, object units

    Returns
    -------
    pieces : (F,) int64, the crease regions, or, where the ends decide, split where a face's end /
        lip class changes
    prob : (P,) fracture likelihood per piece (> 0.5: fracture)
    lips : (F,) bool, the lip faces
    ends : whether the ends decided
    """
    align = wall_end_alignment(centers, normals, areas, wall)
    p_end = 1.0 / (1.0 + np.exp(-np.clip((WALL_END_ALIGN - align) / WALL_END_SOFTNESS, -50, 50)))
    end = p_end > 0.5
    lip = end_lips(centers, areas, topo, align < LIP_CORE_ALIGN, wall)
    e0, e1 = topo.edge_faces[:, 0], topo.edge_faces[:, 1]
    lip |= end & (ring_average(lip.astype(np.float64), np.ones(len(lip)), topo.edge_faces[end[e0] & end[e1]],
                               LIP_GROW_RINGS) > 0)
    ends = end & ~lip
    if areas[ends & (prob[region] > 0.5)].sum() >= WALL_END_COVERED * areas[ends].sum():
        # the crease regions see the band; a region mostly of lip faces is skin (a lip rounded a little)
        n_reg = len(prob)
        lip_share = np.bincount(region, weights=areas * lip, minlength=n_reg) / np.maximum(
            np.bincount(region, weights=areas, minlength=n_reg), 1e-300)
        return region, np.where(lip_share > 0.5, np.minimum(prob, 1.0 - lip_share), prob), lip, False
    face_p = np.where(lip, 0.0, p_end)
    frac = face_p > 0.5
    same = (region[e0] == region[e1]) & (frac[e0] == frac[e1]) & (lip[e0] == lip[e1])
    pieces = components(len(centers), topo.edge_faces[same])
    n = int(pieces.max()) + 1
    piece_p = np.bincount(pieces, weights=areas * face_p, minlength=n) / np.maximum(
        np.bincount(pieces, weights=areas, minlength=n), 1e-300)
    return pieces, piece_p, lip, True


def wall_thickness(centers: np.ndarray, normals: np.ndarray, areas: np.ndarray, skin: np.ndarray,
                   neighbours: int = 24, at_most: int | None = None) -> float:
    """The wall's thickness relative to the piece's size where the skin faces a parallel opposite
    face nearby (a vessel's inner and outer faces), else inf.

    Parameters
    ----------
    centers : (F, 3) face centroids
    normals : (F, 3) unit face normals
    areas : (F,) face areas
    skin : (F,) bool, faces of the grown skin
    neighbours : nearest faces searched for the opposite one
    at_most : of a mesh of more faces, every k-th face is searched, at most this many (None: every
        face). A finer mesh's nearest faces all lie on the skin's own side: rescanned vessel sherds
        of 12,000 faces read as no wall at all, those of 3,000 faces as walls 0.02-0.04 thick.

    Returns
    -------
    float: the area-weighted median distance, along the normal, from a skin face to the nearest
    face turned the other way, over the skin faces that have one, divided by the bounding-box
    diagonal; inf when less than half of the skin has one or the thickness varies (quartiles more
    than a factor 2 apart)
    """
    size = float(np.linalg.norm(centers.max(0) - centers.min(0))) if len(centers) else 0.0
    if not skin.any() or size <= 0 or len(centers) < 4:
        return np.inf
    if at_most is not None and len(centers) > at_most:
        every = np.arange(0, len(centers), -(-len(centers) // at_most))
        centers, normals, areas, skin = centers[every], normals[every], areas[every], skin[every]
    idx = np.flatnonzero(skin)
    if len(idx) == 0:
        return np.inf
    _, near = cKDTree(centers).query(centers[idx], k=min(neighbours, len(centers)), workers=query_threads())
    gap = np.einsum("fkd,fd->fk", centers[idx][:, None] - centers[near], normals[idx])
    opposite = (np.einsum("fkd,fd->fk", normals[near], normals[idx]) < -0.7) & (gap > 0)
    depth = np.where(opposite, gap, np.inf).min(1)
    has = np.isfinite(depth) & (depth > 1e-3 * size)
    total = areas[idx].sum()
    if total <= 0 or areas[idx][has].sum() < 0.5 * total:
        return np.inf  # (a skin of zero area, a reading's degenerate faces, is no wall)
    q25, q50, q75 = weighted_quantile(depth[has], areas[idx][has], [0.25, 0.5, 0.75])
    return float(q50) / size if q75 < 2 * q25 else np.inf  # a wall is about as thick everywhere


def band_shape(centers: np.ndarray, areas: np.ndarray, region: np.ndarray) -> np.ndarray:
    """Per region, the extent of its face centroids along their principal axes and their spread off
    the best-fit plane (object units).

    Parameters
    ----------
    centers : (F, 3) face centroids
    areas : (F,) face areas
    region : (F,) int region id per face, 0..R-1

    Returns
    -------
    (R, 3) float: length (extent along the main axis), bend (extent along the second axis: how far
    a band's centre line curves within its plane) and flat_rms (area-weighted RMS distance of the
    centroids from the plane)
    """
    n_reg = int(region.max()) + 1
    w = np.maximum(np.bincount(region, weights=areas, minlength=n_reg), 1e-300)
    mean = np.stack([np.bincount(region, weights=areas * centers[:, k], minlength=n_reg)
                     for k in range(3)], 1) / w[:, None]
    d = centers - mean[region]
    cov = np.zeros((n_reg, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.bincount(region, weights=areas * d[:, i] * d[:, j], minlength=n_reg) / w
    val, vec = np.linalg.eigh(cov)  # ascending: vec[..., 0] is the plane's normal, vec[..., 2] the main axis
    out = np.zeros((n_reg, 3))
    for col, axis in ((0, 2), (1, 1)):
        t = np.einsum("fd,fd->f", d, vec[region, :, axis])
        hi, lo = np.full(n_reg, -np.inf), np.full(n_reg, np.inf)
        np.maximum.at(hi, region, t)
        np.minimum.at(lo, region, t)
        out[:, col] = hi - lo
    out[:, 2] = np.sqrt(np.maximum(val[:, 0], 0))
    return out
