"""Families of test fractures that `relicgpu.synth` did not make (issue 16, item 1).

A family is a fracture kind crossed with a scan kind, named "<fracture>-<scan>":

fracture kinds (`FRACTURES`)
    rough    a height-field cut: a smooth bend plus fractal sinusoid octaves (RMS ~1.5% of the size)
    smooth   a height-field cut of a few long waves only (curved, no roughness)
    voronoi  flat cuts: the object split into the Voronoi cells of random seeds (Blender's Cell Fracture)
    vessel   a thin-walled open vessel (wall 2-5% of its size) broken by mildly rough cuts
    tetra    the cells of a coarse tetrahedral mesh (edges ~7% of the size) grouped about random seeds: faceted,
             blocky breaks along tetrahedron faces, as Breaking Bad's simulated fractures; any solid, the
             thin vessel among them
scan kinds (`SCANS`)
    clean    the exact boolean pieces, long edges split to the sampling length
    noisy    dense surface samples with noise along the normal (0.02-0.1% of the size), a smoothing
             implicit reconstruction (k-nearest tangent-plane distances, Gaussian blur, marching
             cubes) and decimation to the face budget
    coarse   the exact boolean pieces built coarse: a few hundred faces a piece, CAD-like

The solids (pebble, rounded block, thick jar; thin vessel) and the cutters are made here, with
manifold3d booleans; nothing of synth's fracture code is used. Only synth's conventions are shared:
objects are normalised to a bounding-box diagonal of 1 and centred; results are
`relicgpu.synth.SynthResult`s (write them with `synth.write`), with per fragment the 4x4 pose
carrying its file coordinates into the object frame, the touching pairs (synth's contact rule on
the exact pieces) and per-face fracture labels. Boolean cuts label themselves (a face not from the
original solid is fracture); after a rescan a face takes the label of the nearest exact sample.

Decimation: no quadric decimator is installed (fast-simplification is absent), so the noisy scan
uses manifold3d's error-bounded edge-collapse `simplify`, its tolerance bisected to the face budget.

`realdata(name)` gives the sets of ../shared/realdata with a known answer the same shape: the
Blender Cell Fracture sets keep each file's main body (crumbs dropped), are normalised together,
scattered to random poses, and labelled fracture where a face centre lies within 0.5% of the
object size of another piece.
"""
from __future__ import annotations

import math
import zlib
from pathlib import Path

import numpy as np

from ..io.fragment import Fragment
from .scanning import _invert_rigid, _random_placement
from .truth import SynthResult, _point_triangle_distance, _touching_pairs

FRACTURES = ("rough", "smooth", "voronoi", "vessel", "tetra")
SCANS = ("clean", "noisy", "coarse")
FAMILIES = tuple(f"{f}-{s}" for f in FRACTURES for s in SCANS)
SOLIDS = ("pebble", "block", "jar")  # of the non-vessel kinds, chosen by seed
COARSE_FACES = 300  # faces a piece of a coarse scan, on average
MIN_VOLUME_SHARE = 0.15  # a piece below this share of the mean piece volume makes the cut be drawn again
MAX_ATTEMPTS = 80
REALDATA = Path(__file__).resolve().parents[3] / "shared" / "realdata"
REALDATA_SETS = ("blender_cube_20_seed_2", "blender_cylinder_20_seed_3")
REAL_CONTACT = 0.005  # fracture faces of real sets: within this share of the object size of another piece


# --- the API ---------------------------------------------------------------

def generate(family: str, pieces: int = 2, seed: int = 0, faces: int = 3000, scatter: bool = True) -> SynthResult:
    """Break one object of `family` into `pieces` single-body fragments.

    Parameters
    ----------
    family : str
        One of `FAMILIES`, e.g. "voronoi-noisy".
    pieces : int
        Number of fragments (exactly this many, each one closed body).
    seed : int
        Everything is deterministic under (family, seed).
    faces : int
        Faces a fragment on average for the clean and noisy scans (coarse: `COARSE_FACES`).
    scatter : bool
        Move each fragment to a random pose (truth pose = its inverse), else identity poses.

    Returns
    -------
    SynthResult
        fragments (V_i,3)/(F_i,3); poses (4,4); touching [(i, j)]; fracture_faces (F_i,) bool;
        params["size"] is the object size (largest side of its bounding box, assembled).
    """
    kind, scan = _split_family(family)
    if pieces < 1 or faces < 100:
        raise ValueError(f"pieces >= 1 and faces >= 100 expected, got {pieces}, {faces}")
    ss = np.random.SeedSequence([int(seed), zlib.crc32(family.encode())])
    shape_rng, cut_rng, scan_rng, scatter_rng = (np.random.default_rng(s) for s in ss.spawn(4))
    solids = SOLIDS + ("vessel",) if kind == "tetra" else SOLIDS
    solid_name = "vessel" if kind == "vessel" else solids[int(seed) % len(solids)]
    target = COARSE_FACES if scan == "coarse" else int(faces)
    # sampling length h: triangles of about 0.433 h^2 over the skin and the cut area
    probe, _ = _solid(solid_name, np.random.default_rng(ss.spawn(1)[0]), 0.03)
    area = probe.surface_area() + 0.5 * (pieces - 1) ** 0.8
    h = 1.4 * math.sqrt(area / (0.433 * pieces * target))  # 1.4: measured, refinement and slivers add faces
    obj, wall = _solid(solid_name, shape_rng, h)
    obj_id = obj.original_id()
    cut = {"voronoi": _voronoi, "tetra": _tetra}.get(kind)
    parts = cut(obj, pieces, cut_rng) if cut else _heightfield_cuts(obj, pieces, kind, h, cut_rng)
    if scan == "clean":
        parts = [p.refine_to_length(1.5 * h) for p in parts]
    exact = [_arrays(p, obj_id) for p in parts]
    touching, contact = _touching_pairs([e[0] for e in exact], [e[1] for e in exact])
    lo = np.min([e[0].min(0) for e in exact], axis=0)
    hi = np.max([e[0].max(0) for e in exact], axis=0)
    size = float((hi - lo).max())
    noise = float(scan_rng.uniform(0.0002, 0.001) * size) if scan == "noisy" else 0.0
    meshes = [_rescan(v, f, lab, h, noise, wall, faces, scan_rng) if scan == "noisy" else (v, f, lab)
              for v, f, lab in exact]
    width = max(2, len(str(pieces - 1)))
    fragments, poses = [], []
    for i, (v, f, _) in enumerate(meshes):
        place = _random_placement(v, scatter_rng) if scatter else np.eye(4)
        fragments.append(Fragment(f"frag_{i:0{width}d}", v @ place[:3, :3].T + place[:3, 3], f.astype(np.int32)))
        poses.append(_invert_rigid(place))
    params = {"family": family, "solid": solid_name, "pieces": pieces, "seed": int(seed), "faces": target,
              "spacing": h, "noise": noise, "size": size, "wall": wall, "generator": "relicgpu.corpus"}
    return SynthResult(fragments, poses, touching, f"{family}:{solid_name}", int(seed), params,
                       fracture_faces=[m[2] for m in meshes], contact_areas=contact,
                       object_volume=float(obj.volume()), piece_volumes=[float(p.volume()) for p in parts])


def realdata(name: str, seed: int = 0, root=None, scatter: bool = True) -> SynthResult:
    """A ../shared/realdata set with a known answer (`REALDATA_SETS`), scattered, as a SynthResult.

    Each file's main body (largest area) is kept; all pieces are scaled together to a bounding-box
    diagonal of 1 (`params["scale"]` is the factor). Fracture faces: centre within
    `REAL_CONTACT` x size of another piece. Raises FileNotFoundError where the set is absent.
    """
    import trimesh

    folder = Path(root or REALDATA) / name
    files = sorted(folder.glob("*.ply"))
    if name not in REALDATA_SETS or not files:
        raise FileNotFoundError(f"{folder}: not a realdata set with a known answer here")
    bodies = []
    for p in files:
        m = trimesh.load(p, process=False, force="mesh")
        bodies.append(_main_body(np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)))
    lo = np.min([v.min(0) for v, _ in bodies], axis=0)
    hi = np.max([v.max(0) for v, _ in bodies], axis=0)
    k = 1.0 / float(np.linalg.norm(hi - lo))
    bodies = [((v - 0.5 * (lo + hi)) * k, f) for v, f in bodies]
    size = float((hi - lo).max() * k)
    labels = _near_other(bodies, REAL_CONTACT * size)
    touching, contact = _touching_pairs([v for v, _ in bodies], [f for _, f in bodies])
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), zlib.crc32(name.encode())]))
    fragments, poses = [], []
    for p, (v, f) in zip(files, bodies):
        place = _random_placement(v, rng) if scatter else np.eye(4)
        fragments.append(Fragment(p.stem, v @ place[:3, :3].T + place[:3, 3], f.astype(np.int32)))
        poses.append(_invert_rigid(place))
    params = {"family": name, "pieces": len(files), "seed": int(seed), "size": size, "scale": k,
              "generator": "relicgpu.corpus.realdata"}
    return SynthResult(fragments, poses, touching, name, int(seed), params, fracture_faces=labels,
                       contact_areas=contact)


def object_size(result: SynthResult) -> float:
    """The largest side of the assembled object's bounding box (the issue's unit of length)."""
    placed = result.placed_back()
    lo = np.min([f.vertices.min(0) for f in placed], axis=0)
    hi = np.max([f.vertices.max(0) for f in placed], axis=0)
    return float((hi - lo).max())


# --- solids ----------------------------------------------------------------

def _split_family(family: str) -> tuple[str, str]:
    kind, _, scan = family.partition("-")
    if kind not in FRACTURES or scan not in SCANS:
        raise ValueError(f"unknown family {family!r}; choose from {', '.join(FAMILIES)}")
    return kind, scan


def _manifold(v: np.ndarray, f: np.ndarray):
    """A manifold3d.Manifold from (V,3) vertices and (F,3) outward-wound triangles."""
    import manifold3d as mf

    return mf.Manifold(mf.Mesh(vert_properties=np.ascontiguousarray(v, np.float32),
                               tri_verts=np.ascontiguousarray(f, np.uint32)))


def _arrays(solid, obj_id: int):
    """(V,3) float64, (F,3) int64 and (F,) bool fracture flags (faces not from the original solid)."""
    mesh = solid.to_mesh64()
    v = np.array(mesh.vert_properties, np.float64)[:, :3]
    f = np.array(mesh.tri_verts, np.int64)
    runs = np.diff(np.asarray(mesh.run_index, np.int64)) // 3
    return v, f, np.repeat(np.asarray(mesh.run_original_id) != obj_id, runs)


def _normalised(solid):
    """The solid centred and scaled to a bounding-box diagonal of 1, and the scale factor."""
    x0, y0, z0, x1, y1, z1 = solid.bounding_box()
    lo, hi = np.array([x0, y0, z0]), np.array([x1, y1, z1])
    k = 1.0 / float(np.linalg.norm(hi - lo))
    return solid.translate(list(-0.5 * (lo + hi))).scale([k, k, k]), k


def _solid(name: str, rng: np.random.Generator, h: float):
    """The unbroken solid (an original Manifold, diagonal 1, triangles of about h) and its wall
    thickness in those units (None for solids that are not vessels)."""
    import manifold3d as mf

    j = lambda x, r=0.1: x * (1 + rng.uniform(-r, r))  # noqa: E731
    if name == "pebble":  # an ellipsoid with low bumps
        seg = 4 * max(4, int(2 * math.pi * 0.5 / h / 4))
        m = mf.Manifold.sphere(1.0, seg).to_mesh()
        v = np.array(m.vert_properties, np.float64)[:, :3]
        bump = sum(0.05 * np.sin(v @ rng.normal(0, 2.0, 3) + rng.uniform(0, 2 * np.pi)) for _ in range(4))
        v = v * (1 + bump)[:, None] * np.array([j(0.5), j(0.36), j(0.28)])
        solid = _manifold(v, np.array(m.tri_verts))
    elif name == "block":  # a rounded box: the hull of eight corner balls
        r = j(0.07)
        seg = 4 * max(2, int(2 * math.pi * r / h / 4))
        half = np.array([j(0.5), j(0.32), j(0.2)])
        balls = [mf.Manifold.sphere(r, seg).translate(list(half * np.array(s)))
                 for s in np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T]
        solid = mf.Manifold.batch_hull(balls).refine_to_length(2.5 * h)
    elif name in ("jar", "vessel"):  # a revolved pot: thick walls (jar) or 2-5% of the size (vessel)
        from scipy.interpolate import PchipInterpolator
        height = 1.0
        wall = j(0.09) if name == "jar" else rng.uniform(0.02, 0.05)
        ctrl_r = [j(0.2), j(0.36), j(0.3), j(0.2), j(0.26)] if name == "jar" else [j(0.18), j(0.42), j(0.45), j(0.47), j(0.5)]
        z = np.linspace(0, height, max(8, int(height / h)))
        r_out = PchipInterpolator(np.linspace(0, height, len(ctrl_r)), ctrl_r)(z)
        inner = z >= wall
        poly = np.vstack([[0, 0], np.c_[r_out, z], np.c_[r_out[inner] - wall, z[inner]][::-1], [0, wall]])
        seg = 4 * max(4, int(2 * math.pi * max(ctrl_r) / h / 4))
        solid = mf.Manifold.revolve(mf.CrossSection([poly]), seg)
    else:
        raise ValueError(f"unknown solid {name!r}")
    solid, k = _normalised(solid)
    return solid.as_original(), (wall * k if name == "vessel" else None)


# --- cutting ---------------------------------------------------------------

def _frame(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(helper, n)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def _height_function(kind: str, rng: np.random.Generator, h: float):
    """z(a, b) of a cut surface, object units: long waves (all kinds) plus fractal octaves (rough, vessel)."""
    waves = []  # (direction (2,), wavenumber, phase, amplitude)
    bend = {"smooth": 0.035, "rough": 0.012, "vessel": 0.01}[kind]
    for _ in range(3):
        waves.append((rng.normal(size=2), 2 * np.pi / rng.uniform(0.5, 1.2), rng.uniform(0, 2 * np.pi), bend))
    if kind in ("rough", "vessel"):
        amp, wavelength = (0.009 if kind == "rough" else 0.004), 0.16
        while wavelength > 3 * h:
            for _ in range(5):
                waves.append((rng.normal(size=2), 2 * np.pi / wavelength, rng.uniform(0, 2 * np.pi), amp))
            amp, wavelength = amp * 0.55, wavelength * 0.5
    def z(a, b):
        out = np.zeros_like(a)
        for d, k, ph, amp in waves:
            d = d / np.linalg.norm(d)
            out += amp * np.sin(k * (d[0] * a + d[1] * b) + ph)
        return out
    return z


def _cutter(point: np.ndarray, normal: np.ndarray, radius: float, h: float, zfun):
    """A closed solid below the surface point + a u + b w + z(a, b) normal, |a|, |b| <= radius."""
    n = max(4, int(math.ceil(2 * radius / h)))
    g = np.linspace(-radius, radius, n + 1)
    A, B = np.meshgrid(g, g, indexing="ij")
    top = np.c_[A.ravel(), B.ravel(), zfun(A, B).ravel()]
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    q0, q1, q2, q3 = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = [np.c_[q0, q1, q2], np.c_[q0, q2, q3]]
    ring = np.concatenate([idx[:, 0], idx[-1, 1:], idx[-2::-1, -1], idx[0, -2:0:-1]])  # counter-clockwise
    depth = radius + 0.1
    bottom = top[ring] * [1, 1, 0] - [0, 0, depth]
    nb = len(top)
    b = nb + np.arange(len(ring))
    centre = nb + len(ring)
    t1, b1 = np.roll(ring, -1), np.roll(b, -1)
    faces += [np.c_[ring, b, b1], np.c_[ring, b1, t1], np.c_[np.full(len(b), centre), b1, b]]
    v = np.vstack([top, bottom, [[0, 0, -depth]]])
    u, w = _frame(normal)
    v = point + v[:, :1] * u + v[:, 1:2] * w + v[:, 2:] * normal
    return _manifold(v, np.vstack(faces)).as_original()


def _single(solid, min_volume: float) -> bool:
    return len(solid.decompose()) == 1 and solid.volume() > min_volume


def _heightfield_cuts(obj, pieces: int, kind: str, h: float, rng: np.random.Generator) -> list:
    """Split the largest piece by a random height-field cut until there are `pieces` single bodies."""
    parts = [obj]
    min_volume = MIN_VOLUME_SHARE * obj.volume() / pieces
    while len(parts) < pieces:
        k = int(np.argmax([p.volume() for p in parts]))
        part = parts[k]
        x0, y0, z0, x1, y1, z1 = part.bounding_box()
        lo, hi = np.array([x0, y0, z0]), np.array([x1, y1, z1])
        for _ in range(MAX_ATTEMPTS):
            point = 0.5 * (lo + hi) + rng.uniform(-0.15, 0.15, 3) * (hi - lo)
            normal = rng.normal(size=3)
            normal /= np.linalg.norm(normal)
            radius = 0.5 * float(np.linalg.norm(hi - lo)) + float(np.linalg.norm(point - 0.5 * (lo + hi))) + 0.05
            cut = _cutter(point, normal, radius, h, _height_function(kind, rng, h))
            a, b = part ^ cut, part - cut
            if _single(a, min_volume) and _single(b, min_volume):
                parts[k:k + 1] = [a, b]
                break
        else:
            raise RuntimeError(f"corpus: no clean {kind} cut of a piece in {MAX_ATTEMPTS} attempts")
    return parts


def _voronoi(obj, pieces: int, rng: np.random.Generator) -> list:
    """The object split into the Voronoi cells of `pieces` random seeds, every cell one body."""
    x0, y0, z0, x1, y1, z1 = obj.bounding_box()
    lo, hi = np.array([x0, y0, z0]), np.array([x1, y1, z1])
    min_volume = MIN_VOLUME_SHARE * obj.volume() / pieces
    for _ in range(MAX_ATTEMPTS):
        seeds = lo + (hi - lo) * rng.uniform(0.15, 0.85, (pieces, 3))
        cells = []
        for i in range(pieces):
            cell = obj
            for jj in range(pieces):
                if jj != i:
                    d = seeds[i] - seeds[jj]
                    n = d / np.linalg.norm(d)
                    cell = cell.trim_by_plane(list(n), float(n @ (0.5 * (seeds[i] + seeds[jj]))))
            if not _single(cell, min_volume):
                break
            cells.append(cell)
        if len(cells) == pieces:
            return cells
    raise RuntimeError(f"corpus: no {pieces} single-body Voronoi cells in {MAX_ATTEMPTS} draws")


def _tetra(obj, pieces: int, rng: np.random.Generator, spacing: float = 0.08) -> list:
    """The object split along the faces of a tetrahedral mesh (body-centred cubic points at `spacing`,
    jittered): each tetrahedron goes to the nearest of `pieces` random seeds; a cell's stray bodies
    join the neighbouring piece they fuse with."""
    import manifold3d as mf
    from scipy.spatial import Delaunay

    # the box rounded out, so that the object made at another resolution is cut by the same cells
    box = np.array(obj.bounding_box())
    lo, hi = np.floor(box[:3] / 0.05) * 0.05, np.ceil(box[3:] / 0.05) * 0.05
    axes = [np.arange(lo[d] - spacing, hi[d] + 2 * spacing, spacing) for d in range(3)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    g = np.vstack([g, g + 0.5 * spacing])  # body-centred cubic: well-shaped tetrahedra
    g += rng.uniform(-0.12, 0.12, g.shape) * spacing
    tets = Delaunay(g).simplices
    p = g[tets]
    inverted = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) < 0
    tets[inverted] = tets[inverted][:, [0, 2, 1, 3]]
    centre = g[tets].mean(1)
    sides = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    min_volume = MIN_VOLUME_SHARE * obj.volume() / pieces
    for _ in range(MAX_ATTEMPTS):
        seeds = lo + (hi - lo) * rng.uniform(0.15, 0.85, (pieces, 3))
        owner = np.argmin(((centre[:, None] - seeds[None]) ** 2).sum(-1), axis=1)
        main, strays = [], []
        for i in range(pieces):
            cell = mf.Manifold.batch_boolean([_manifold(g[t], sides) for t in tets[owner == i]], mf.OpType.Add)
            bodies = sorted((obj ^ cell).decompose(), key=lambda s: -s.volume())
            if not bodies or bodies[0].volume() < min_volume:
                break
            main.append(bodies[0])
            strays += bodies[1:]
        else:
            for stray in strays:
                joined = next((k for k, m in enumerate(main) if len((m + stray).decompose()) == 1), None)
                if joined is None:
                    break
                main[joined] = main[joined] + stray
            else:
                return main
    raise RuntimeError(f"corpus: no {pieces} single-body tetrahedral cells in {MAX_ATTEMPTS} draws")


# --- scanning --------------------------------------------------------------

def _surface_samples(v, f, count, rng):
    """(N,3) points uniform on the surface, (N,3) their face normals, (N,) their face ids."""
    tri = v[f]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(cross, axis=1)
    face = rng.choice(len(f), count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    p = tri[face, 0] * (1 - s)[:, None] + tri[face, 1] * (s * (1 - r2))[:, None] + tri[face, 2] * (s * r2)[:, None]
    n = cross[face] / np.maximum(area[face], 1e-300)[:, None]
    return p, n, face


def _rescan(v, f, label, h, noise, wall, faces, rng):
    """A noisy dense scan of one exact piece, reconstructed and decimated to about `faces` faces.

    Returns (V,3), (F,3) and (F,) fracture labels taken from the nearest noise-free sample.
    """
    from scipy.ndimage import gaussian_filter, label as components
    from scipy.spatial import cKDTree
    from skimage.measure import marching_cubes

    voxel = min(h / 2.5, (wall or 1.0) / 3.5, 0.01)  # a dense scan: finer than the decimated mesh
    area = float(np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum() / 2)
    exact, normal, face = _surface_samples(v, f, int(min(400_000, 6 * area / voxel ** 2)), rng)
    pts = exact + normal * rng.normal(0.0, noise, (len(exact), 1)) if noise else exact
    lo = v.min(0) - 4 * voxel
    axes = [np.arange(lo[d], v.max(0)[d] + 4 * voxel, voxel) for d in range(3)]
    shape = [len(a) for a in axes]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    # near the samples: a weighted mean of the tangent-plane distances of the 8 nearest samples that
    # face the same way as the nearest (the two sides of a thin wall do not blend)
    d8, i8 = cKDTree(pts).query(grid, k=8, distance_upper_bound=2.5 * voxel)
    band = np.flatnonzero(np.isfinite(d8[:, 0]))
    d8, i8 = d8[band], np.minimum(i8[band], len(pts) - 1)
    same_side = np.einsum("ikj,ij->ik", normal[i8], normal[i8[:, 0]]) > 0.3
    w = np.exp(-(d8 / (1.5 * voxel)) ** 2) * same_side * np.isfinite(d8)
    plane = np.einsum("ikj,ikj->ik", grid[band][:, None] - pts[i8], normal[i8])
    sdf = np.full(len(grid), 3 * voxel)
    sdf[band] = (w * plane).sum(1) / np.maximum(w.sum(1), 1e-12)
    sdf = sdf.reshape(shape)
    # off the band: outside where connected to the grid's border, else inside
    off = np.ones(len(grid), bool)
    off[band] = False
    comp, _ = components(off.reshape(shape))
    border = np.unique(np.concatenate([comp[[0, -1]].ravel(), comp[:, [0, -1]].ravel(), comp[:, :, [0, -1]].ravel()]))
    sdf[(comp > 0) & ~np.isin(comp, border)] = -3 * voxel
    mv, mf_, _, _ = marching_cubes(gaussian_filter(sdf, 0.6), 0.0, spacing=(voxel,) * 3, allow_degenerate=False)
    solid = _manifold(mv + lo, mf_)
    if solid.volume() < 0:
        solid = _manifold(mv + lo, mf_[:, ::-1])
    solid = max(solid.decompose(), key=lambda s: s.volume())
    solid = _decimate(solid, faces, min(h, wall or h) / 4)
    mesh = solid.to_mesh64()
    nv = np.array(mesh.vert_properties, np.float64)[:, :3]
    nf = np.array(mesh.tri_verts, np.int64)
    _, nearest = cKDTree(exact).query(nv[nf].mean(1))
    return nv, nf, label[face[nearest]]


def _decimate(solid, faces: int, max_tolerance: float):
    """Error-bounded edge collapse (manifold3d simplify) at the smallest of a sweep of tolerances up
    to `max_tolerance` that reaches about `faces` triangles, else the fewest triangles of the sweep
    (beyond a wall's scale simplify starts to add triangles again, so the sweep stops there)."""
    if solid.num_tri() <= faces:
        return solid
    best = solid
    for tol in max_tolerance * np.geomspace(1 / 100, 1, 8):
        s = solid.simplify(float(tol))
        if s.num_tri() < best.num_tri():
            best = s
        if s.num_tri() <= 1.15 * faces:
            break
    return best


# --- real sets -------------------------------------------------------------

def _main_body(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The connected body of largest area of a mesh (crumbs and chips dropped), vertices renumbered."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]]])
    _, comp = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(len(v), len(v))),
                                   directed=False)
    area = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    keep = comp[f[:, 0]] == np.argmax(np.bincount(comp[f[:, 0]], weights=area))
    used, f2 = np.unique(f[keep], return_inverse=True)
    return v[used], f2.reshape(-1, 3)


def _near_other(bodies: list, d: float, k: int = 16) -> list[np.ndarray]:
    """Per body (F_i,) bool: its face centre lies within d of another body's surface.

    Triangles of radius above 4 d (few: long skinny fans) are tested against every centre near
    them; the others among the k with the nearest centres."""
    from scipy.spatial import cKDTree

    out = []
    for i, (v, f) in enumerate(bodies):
        centre = v[f].mean(1)
        best = np.full(len(f), np.inf)
        for j, (w, g) in enumerate(bodies):
            near = np.flatnonzero(((centre >= w.min(0) - d) & (centre <= w.max(0) + d)).all(1))
            if j == i or len(near) == 0:
                continue
            tri = w[g]
            radius = np.linalg.norm(tri - tri.mean(1)[:, None], axis=2).max(1)
            small, big = np.flatnonzero(radius <= 4 * d), np.flatnonzero(radius > 4 * d)
            big = big[((tri[big].max(1) >= v.min(0) - d) & (tri[big].min(1) <= v.max(0) + d)).all(1)]
            p = centre[near]
            if len(small):
                kk = min(k, len(small))
                dist, idx = cKDTree(tri[small].mean(1)).query(p, k=kk, distance_upper_bound=5 * d)
                dist, idx = dist.reshape(len(p), kk), idx.reshape(len(p), kk)
                row, col = np.nonzero(np.isfinite(dist))
                t = tri[small[idx[row, col]]]
                dd = _point_triangle_distance(p[row], t[:, 0], t[:, 1], t[:, 2])
                np.fmin.at(best, near[row], dd)  # fmin: a degenerate triangle's nan is skipped
            for b in big:  # per big triangle, the centres within its box
                hit = np.flatnonzero(((p >= tri[b].min(0) - d) & (p <= tri[b].max(0) + d)).all(1))
                if len(hit):
                    t = np.repeat(tri[b][None], len(hit), 0)
                    dd = _point_triangle_distance(p[hit], t[:, 0], t[:, 1], t[:, 2])
                    best[near[hit]] = np.fmin(best[near[hit]], dd)
        out.append(best <= d)
    return out
