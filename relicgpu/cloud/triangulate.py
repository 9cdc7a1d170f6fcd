"""Point-cloud fragments: read raw scans and triangulate them into closed meshes.

Paper sections 3.5 (scanners deliver point clouds, .asc and .pcd) and 3.7.1
(Delaunay triangulation before segmentation). The paper hand-codes
Bowyer-Watson; here the Delaunay step is Qhull's (scipy.spatial.Delaunay) in
3-D, and the surface is carved out of the tetrahedralisation:

1. Thin the cloud on a voxel grid (the mean of the points of each voxel) when it
   has more than `max_points` points, so that Qhull stays fast.
2. Delaunay-tetrahedralise the points (scaled into [-1, 1], jittered by 1e-9).
3. Flood the tetrahedra from outside the convex hull through every face whose
   circumradius exceeds alpha. A surface sampled at spacing h is sealed by
   Delaunay triangles of circumradius about h, so the flood stops at the scanned
   surface; what it does not reach is inside. alpha starts at ALPHA_FACTOR times
   the median nearest-neighbour distance and grows until the flood stops leaking
   through gaps in the scan: the inside holds (nearly) every point and its volume
   no longer grows with alpha.
4. Keep the largest face-connected inside body; a majority vote over face
   neighbours removes lone slivers that would pinch the surface.
5. Peel: a tetrahedron under a boundary face whose fourth point lies just below
   that face is moved outside, so the surface passes through points the large
   alpha had spanned over (sculpting, which keeps the surface a manifold).
6. The boundary triangles, wound away from their inside tetrahedron (outwards),
   form the mesh. Where the surface still touches itself (an edge with four
   faces, a vertex with two fans) it is split into separate sheets, small sheets
   pinched off are dropped, and the copies of a split point are moved 10% into
   their own sheets, so that the result is one closed manifold with no two
   vertices at one place.
7. Refine: the boundary of a Delaunay tetrahedralisation of random samples holds
   triangles standing across the surface (where four samples are nearly
   co-circular) and, with scanner noise, rough ones everywhere. The segmentation
   reads rough triangles as fracture surface, so (a) edges are flipped where the
   two new triangles agree better with the cloud's normals (principal axes of the
   nearest NORMAL_NEIGHBOURS points), (b) each vertex moves to the point nearest
   to the planes of the triangles within SMOOTH_RINGS edge steps (a quadric, with
   a pull of SMOOTH_STAY to where it was, so it slides little along the surface,
   creases keep their place and rough fracture stays rough), (c) edges are flipped
   again. Flips keep the mesh a closed manifold.

Limits: features smaller than alpha (a few point spacings) are bridged, walls
need a few spacings of thickness, a scan with holes wider than alpha is closed
over them (with a note), and the scan must cover the whole fragment: a one-sided
scan is not a solid.
"""
from __future__ import annotations

import sys
import time
import weakref
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..io.clouds import _check_points, MIN_POINTS, read_point_cloud
from ..errors import CliError
from ..io.files import ensure_not_input, write_mesh
from ..io.meshes import MESH_SUFFIXES
from ..io.fragment import Fragment, fragment_from_arrays, FragmentError, is_cloud
from .points import _median_spacing, choose_voxel, cloud_fragment, voxel_thin
from .refine import closed_manifold_fault, decimate, refine_surface
from .tets import _boundary, _largest_body, _OUT_FACES, _outside_by_flood, _surface, _Tets

# Qhull takes about 6 s per 200k surface points on the project's CPU: 400k
# points keep one Delaunay near 15 s and the whole meshing of a 1M-point scan
# well inside a minute. Above this the cloud is thinned on a voxel grid.
MAX_POINTS = 400_000
# alpha = ALPHA_FACTOR * median nearest-neighbour distance, grown by
# ALPHA_GROWTH when the flood leaks, at most ALPHA_TRIES times.
ALPHA_FACTOR = 2.5
ALPHA_GROWTH = 1.25
ALPHA_TRIES = 12
# A flood that leaves more than 2% of the points outside the body has leaked;
# one whose volume grows by more than 10% at the next alpha has not settled.
MIN_COVERAGE = 0.98
STABLE_VOLUME = 0.9
# Points buried under the sealed surface by at most PEEL_DEPTH spacings are
# uncovered (noise, curvature); deeper ones are taken to belong to another sheet.
PEEL_DEPTH = 1.0
PEEL_ROUNDS = 30
# Rounds of the majority vote that removes lone slivers from the inside/outside labels.
SMOOTH_ROUNDS = 3
# Copies of a point where the surface touches itself move this fraction of the way
# to the centre of their own ring of neighbours.
SPLIT_NUDGE = 0.1
# load_fragment meshes a cloud at up to DENSE_POINTS points, then decimates the mesh to
# MATCH_FACES: the density at which the matcher's segmentation was measured to work (see
# tests/test_pointcloud.py). Thinning the cloud to MATCH_POINTS before meshing (the fallback) costs
# accuracy: synth torso pieces, 60,000 points, Gaussian noise 0.05% of the largest side, came within
# 0.82-1.40% of that side of their source (Hausdorff) that way, 0.71-0.80% meshed dense and
# decimated (docs/benchmarks.md, "Dense clouds meshed dense").
DENSE_POINTS = 100_000
MATCH_FACES = 24_000
MATCH_POINTS = MATCH_FACES // 2
# A cloud of fewer than MATCH_POINTS points would make a mesh coarser than that density: it is
# matched on its points, with the normals it was scanned with. Meshed, a sparse thin board's cloud
# closes into a slab the segmentation misreads, and the scan's normals are lost (2,500 points a
# piece, docs/benchmarks.md "Sparse clouds in files"). A cloud scanned with normals is matched on its
# points at any density (thinned evenly to `Params.cloud_points` by the matcher): meshed, a dense
# one loses its normals and a thin wall closes into a slab (docs/benchmarks.md, "Dense clouds with
# normals matched on their points, thinned").


@dataclass(frozen=True)
class MeshResult:
    """A closed triangle mesh made from a point cloud, and how it was made."""
    vertices: np.ndarray  # (V,3) float64
    faces: np.ndarray  # (F,3) int32, wound outwards
    n_input: int  # points given
    n_meshed: int  # points after voxel thinning
    voxel: float  # voxel edge used for thinning (0: none)
    spacing: float  # median nearest-neighbour distance of the meshed points
    alpha: float  # final flood threshold (circumradius)
    coverage: float  # fraction of the meshed points that are mesh vertices
    timings: dict = field(default_factory=dict)
    notes: tuple[str, ...] = ()


def _boundary_counts(tets: _Tets, inside: np.ndarray) -> np.ndarray:
    """(T,4) True where face k of an inside tetrahedron lies on the boundary."""
    nb = tets.neighbors
    nb_inside = np.where(nb >= 0, inside[np.maximum(nb, 0)], False)
    return inside[:, None] & ~nb_inside


def _peel(tets: _Tets, inside: np.ndarray, depth: float, max_rounds: int = PEEL_ROUNDS):
    """Uncover points buried just under the surface, keeping it a manifold.

    A large alpha seals the surface but spans some triangles over points a little
    below them (scanner noise, curvature). A tetrahedron with one boundary face and
    its fourth vertex buried under that face, less than `depth` below it, is moved
    outside: the face gives way to three faces through the buried point (the
    sculpting step of Boissonnat, 1984). Several such steps at once stay a manifold
    as long as their buried points differ.
    """
    q, nb, simplices = tets.q, tets.neighbors, tets.simplices
    inside = inside.copy()
    on_surface = np.zeros(tets.n_points, bool)
    faces, _ = _boundary(tets, inside)
    on_surface[faces.ravel()] = True
    active = np.nonzero(inside)[0]
    peeled = 0
    for _ in range(max_rounds):
        # Only tetrahedra next to the last round's changes can have become eligible.
        active = active[inside[active]]
        nbr = nb[active]
        nb_in = np.where(nbr >= 0, inside[np.maximum(nbr, 0)], False)
        bnd = ~nb_in
        one = bnd.sum(axis=1) == 1
        t = active[one]
        k = np.argmax(bnd[one], axis=1)
        apex = simplices[t, k]
        ok = ~on_surface[apex]
        t, k, apex = t[ok], k[ok], apex[ok]
        if len(t) == 0:
            break
        tri = np.take_along_axis(simplices[t], _OUT_FACES[k], axis=1)
        a, b, c, d = q[tri[:, 0]], q[tri[:, 1]], q[tri[:, 2]], q[apex]
        normal = np.cross(b - a, c - a)
        n2 = np.einsum("ij,ij->i", normal, normal)
        h = np.abs(np.einsum("ij,ij->i", d - a, normal)) / np.sqrt(np.maximum(n2, 1e-300))
        # The apex must lie under the face (barycentric coordinates of its projection >= 0),
        # else one of the three new faces would fold over its neighbours.
        under = (n2 > 0) & (h <= depth)
        for u, v in ((a, b), (b, c), (c, a)):
            under &= np.einsum("ij,ij->i", np.cross(v - u, d - u), normal) >= 0
        t, k, apex = t[under], k[under], apex[under]
        if len(t) == 0:
            break
        # One tetrahedron per buried point and round: the one under the biggest face.
        order = np.argsort(-tets.face_radius[t, k], kind="stable")
        _, first = np.unique(apex[order], return_index=True)
        chosen = t[order[first]]
        inside[chosen] = False
        on_surface[simplices[chosen].ravel()] = True
        peeled += len(chosen)
        nxt = nb[chosen].ravel()
        active = np.unique(nxt[nxt >= 0])
    return inside, peeled


def _smooth_labels(tets: _Tets, inside: np.ndarray, alpha: float, rounds: int = SMOOTH_ROUNDS) -> np.ndarray:
    """A majority vote over face neighbours: fill local outside tetrahedra with three or four
    inside neighbours, carve inside ones with at most one. The flood leaves such lone slivers
    along the surface, and each pinches it (two sheets meeting at a vertex or an edge)."""
    nb = tets.neighbors
    local = tets.longest <= 2.0 * alpha
    for _ in range(rounds):
        n_inside = np.where(nb >= 0, inside[np.maximum(nb, 0)], False).sum(axis=1)
        add = ~inside & (n_inside >= 3) & local
        cut = inside & (n_inside <= 1)
        if not add.any() and not cut.any():
            break
        inside = (inside | add) & ~cut
    return inside


def triangulate(points, *, max_points: int | None = MAX_POINTS, alpha_factor: float = ALPHA_FACTOR,
                refine: bool = True, progress: bool = False, label: str = "points",
                debug: bool = False) -> MeshResult:
    """Mesh a point cloud sampled from the surface of one solid into a closed, outward-wound triangle mesh.

    max_points: thin larger clouds on a voxel grid first (None: never).
    alpha_factor: the first alpha, in median point spacings (it grows while the flood leaks).
    refine: flip edges and move vertices towards the cloud's surface (step 7 of the module notes).
    debug: print the figures of each alpha tried to stderr.
    """
    from tqdm import tqdm

    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise FragmentError(f"{label}: points must be an (N, 3) array, got shape {pts.shape}")
    _check_points(pts, label)
    timings: dict[str, float] = {}
    notes: list[str] = []
    bar = tqdm(total=6, desc=f"mesh {Path(label).name}", unit="step", disable=not progress, file=sys.stderr, leave=False)
    t0 = time.perf_counter()
    voxel = 0.0
    if max_points and len(pts) > max_points:
        voxel = choose_voxel(pts, max_points)
        pts = voxel_thin(pts, voxel)
        notes.append(f"{label}: thinned {len(points)} points to {len(pts)} on a voxel grid of {voxel:.4g}")
    timings["thin"] = time.perf_counter() - t0
    bar.update()

    # Centre and scale for Qhull: its tolerances are relative to the coordinates.
    centre = 0.5 * (pts.min(0) + pts.max(0))
    scale = float(np.abs(pts - centre).max())
    if not scale > 0:
        raise FragmentError(f"{label}: all points coincide")
    q = (pts - centre) / scale
    # Points in a plane (or on a line) bound no solid; the jitter below would hide that from Qhull.
    sample = q[:: max(1, len(q) // 20000)]
    thinnest = np.linalg.svd(sample - sample.mean(0), compute_uv=False)[-1] / np.sqrt(len(sample))
    if thinnest < 1e-7:
        raise FragmentError(f"{label}: the points span no volume (they lie in a plane or on a line)")
    t0 = time.perf_counter()
    spacing = _median_spacing(q)
    if not spacing > 0:
        raise FragmentError(f"{label}: the points have no distinct neighbours")
    timings["spacing"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    try:
        tets = _Tets(q)
    except FragmentError as exc:
        raise FragmentError(f"{label}: {exc}") from None
    timings["delaunay"] = time.perf_counter() - t0
    bar.update()

    # Below some alpha the flood leaks into the body through gaps in the scan and leaves
    # almost nothing inside; above it the inside volume barely grows with alpha. Take the
    # smallest alpha whose body holds (nearly) all the points and whose volume is stable.
    t0 = time.perf_counter()
    tries = []
    chosen = None
    for attempt in range(ALPHA_TRIES):
        alpha = alpha_factor * spacing * ALPHA_GROWTH ** attempt
        inside = ~_outside_by_flood(tets, alpha)
        held = np.zeros(len(q), bool)
        held[tets.simplices[inside].ravel()] = True
        volume = float(np.abs(tets.volume6[inside]).sum())
        tries.append((alpha, inside, float(held.mean()), volume))
        if debug:
            print(f"alpha {alpha / spacing:.2f}x spacing: points held {held.mean():.3f}, "
                  f"volume {volume / 6 * scale ** 3:.4g}", file=sys.stderr)
        if len(tries) >= 2:
            before, now = tries[-2], tries[-1]
            if before[2] >= MIN_COVERAGE and before[3] >= STABLE_VOLUME * now[3]:
                chosen = before
                break
    timings["carve"] = time.perf_counter() - t0
    bar.update()
    if chosen is None:
        if tries[-1][2] < MIN_COVERAGE:
            raise FragmentError(f"{label}: no closed surface found up to alpha {alpha * scale:.4g} "
                                "(is this the scan of one solid, without large holes?)")
        chosen = tries[-1]
        notes.append(f"{label}: the enclosed volume still grows at alpha {chosen[0] * scale:.4g}; "
                     "the scan may have large holes")
    alpha, inside = chosen[:2]
    inside, n_bodies, _ = _largest_body(tets, inside)
    if alpha > alpha_factor * spacing:
        notes.append(f"{label}: alpha grown to {alpha / spacing:.2f} point spacings to seal gaps in the scan")
    if n_bodies > 1:
        notes.append(f"{label}: kept the largest of {n_bodies} separate bodies")

    t0 = time.perf_counter()
    inside, _, _ = _largest_body(tets, _smooth_labels(tets, inside, alpha))
    inside, _ = _peel(tets, inside, PEEL_DEPTH * spacing)
    timings["peel"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    surface = _surface(tets, inside)
    if len(surface.faces) == 0:
        raise FragmentError(f"{label}: no closed surface found (is this the scan of one solid?)")
    faces, source = surface.faces, surface.source
    comp_sizes = np.bincount(surface.component)
    if len(comp_sizes) > 1:
        keep = surface.component == int(np.argmax(comp_sizes))
        notes.append(f"{label}: dropped {len(comp_sizes) - 1} small sheets ({int((~keep).sum())} faces) "
                     "pinched off the main surface")
        faces = faces[keep]
    if not surface.closed:
        notes.append(f"{label}: some edges are still shared by more than two faces")
    if surface.inconsistent:
        notes.append(f"{label}: {surface.inconsistent} edges are wound inconsistently")

    used = np.unique(faces)
    remap = np.full(len(source), -1, np.int64)
    remap[used] = np.arange(len(used))
    source = source[used]
    faces = remap[faces]
    vertices = pts[source]
    # Where the surface touches itself (a point split into several copies, one per sheet),
    # move each copy a little into its own sheet so that no two vertices coincide.
    copies = np.bincount(source, minlength=len(pts))
    split = copies[source] > 1
    if split.any():
        ring = np.zeros_like(vertices)
        corner_v = faces.ravel()
        nbr_sum = vertices[np.roll(faces, -1, axis=1)].reshape(-1, 3) + vertices[np.roll(faces, 1, axis=1)].reshape(-1, 3)
        for axis in range(3):
            ring[:, axis] = np.bincount(corner_v, nbr_sum[:, axis], minlength=len(vertices))
        count = 2.0 * np.bincount(corner_v, minlength=len(vertices))
        centre_of_ring = ring / np.maximum(count, 1)[:, None]
        vertices = vertices.copy()
        vertices[split] += SPLIT_NUDGE * (centre_of_ring[split] - vertices[split])
        notes.append(f"{label}: the surface touched itself at {int((copies > 1).sum())} points; "
                     f"their copies were moved {SPLIT_NUDGE:.0%} of the way into their own sheets")
    faces = faces.astype(np.int32)
    coverage = len(np.unique(source)) / len(q)
    timings["repair"] = time.perf_counter() - t0
    bar.update()
    if refine:
        t0 = time.perf_counter()
        refined = refine_surface(vertices, faces, pts)
        if refined is None:
            notes.append(f"{label}: the surface was left unrefined (some edges are not shared by exactly two faces)")
        else:
            vertices, faces = refined
        timings["refine"] = time.perf_counter() - t0
    bar.update()
    bar.close()
    return MeshResult(vertices, faces, len(points), len(pts), voxel, spacing * scale, alpha * scale,
                      coverage, timings, tuple(notes))


def mesh_for_matching(points, *, max_points: int | None = DENSE_POINTS, faces: int | None = MATCH_FACES,
                      alpha_factor: float = ALPHA_FACTOR, refine: bool = True, progress: bool = False,
                      label: str = "points") -> MeshResult:
    """`triangulate` at up to max_points points, then `refine.decimate` to at most about `faces`
    faces (None: as meshed), or, where the dense mesh cannot be decimated, the cloud thinned to
    faces // 2 points (a closed surface has about twice as many faces as vertices) and meshed.
    Raises FragmentError as `triangulate` does."""
    result = triangulate(points, max_points=max_points, alpha_factor=alpha_factor, refine=refine,
                         progress=progress, label=label)
    if faces is None or len(result.faces) <= faces:
        return result
    thinner = decimate(result.vertices, result.faces, faces)
    if thinner is not None and closed_manifold_fault(thinner[0], thinner[1]) is None:
        v, f, tolerance = thinner
        note = (f"{label}: {len(result.faces)} faces decimated to {len(f)} for matching "
                f"(surface moved at most {tolerance:.3g})")
        return replace(result, vertices=v, faces=f, notes=result.notes + (note,))
    again = triangulate(points, max_points=max(faces // 2, MIN_POINTS), alpha_factor=alpha_factor, refine=refine,
                        progress=progress, label=label)
    note = f"{label}: the dense mesh could not be decimated; the cloud was thinned before meshing instead"
    return replace(again, notes=again.notes + (note,))


# each cloud's surface (or its FragmentError) while the cloud lives: `relicgpu group` describes a
# heap's clouds by their surfaces and then writes each object's merged.stl of the same clouds
# (meshing a 20,000-point cloud takes 3 s)
_SURFACES: "weakref.WeakKeyDictionary[Fragment, Fragment | FragmentError]" = weakref.WeakKeyDictionary()


def surface_of(fragment: Fragment) -> Fragment:
    """The fragment, or a point cloud's surface meshed as a dense cloud is for matching
    (`mesh_for_matching`), once per cloud: grouping's descriptors and merged.stl need a surface,
    which a cloud matched on its points still has where it closes. FragmentError where it does
    not close into a solid."""
    if not is_cloud(fragment):
        return fragment
    surface = _SURFACES.get(fragment)
    if surface is None:
        try:
            mesh = mesh_for_matching(fragment.vertices, label=fragment.source or fragment.name)
            surface = fragment_from_arrays(fragment.name, mesh.vertices, mesh.faces, source=fragment.source)
        except FragmentError as exc:
            surface = exc
        _SURFACES[fragment] = surface
    if isinstance(surface, FragmentError):
        raise FragmentError(str(surface))
    return surface


def load_point_cloud_fragment(path, name: str | None = None, *, max_points: int | None = DENSE_POINTS,
                              faces: int = MATCH_FACES, alpha_factor: float = ALPHA_FACTOR,
                              progress: bool = False) -> Fragment:
    """Read a point-cloud file and mesh it for matching (`mesh_for_matching`) into a checked
    Fragment (called by relicgpu.io.load_fragment); a cloud with normals, one of fewer than
    MATCH_POINTS points, or one that does not close into a solid becomes a CloudFragment, matched
    on its points. `relicgpu mesh` makes a mesh of any cloud to keep.
    """
    p = Path(path)
    cloud = read_point_cloud(p)
    if cloud.normals is not None:
        why = f"{p}: {len(cloud.points)} points with normals; matched on its points and their normals"
        return cloud_fragment(name or p.stem, cloud.points, cloud.normals, str(p), cloud.notes + (why,))
    if len(cloud.points) < MATCH_POINTS:
        why = (f"{p}: {len(cloud.points)} points, fewer than the {MATCH_POINTS} a mesh for matching needs; "
               "matched on its points")
        return cloud_fragment(name or p.stem, cloud.points, None, str(p), cloud.notes + (why,))
    try:
        result = mesh_for_matching(cloud.points, max_points=max_points, faces=faces, alpha_factor=alpha_factor,
                                   progress=progress, label=str(p))
    except FragmentError as exc:  # sparse, thin or open: no solid, matched on its points
        return cloud_fragment(name or p.stem, cloud.points, cloud.normals, str(p),
                              cloud.notes + (f"{exc}; matched on its points",))
    frag = fragment_from_arrays(name or p.stem, result.vertices, result.faces, source=str(p))
    summary = (f"{p}: triangulated {result.n_input} points ({result.n_meshed} meshed) into "
               f"{len(result.faces)} faces, alpha {result.alpha:.4g}")
    return Fragment(frag.name, frag.vertices, frag.faces, frag.source,
                    cloud.notes + result.notes + frag.notes + (summary,))


# --- command line ----------------------------------------------------------

def cli_add_arguments(parser) -> None:
    parser.add_argument("cloud", help="point cloud: .xyz/.asc/.txt, .pcd, .ply without faces, or .npy")
    parser.add_argument("-o", "--output", help="mesh file to write (.ply, .stl, .obj, .off, .glb); "
                        "default: CLOUD_mesh.ply beside the input")
    parser.add_argument("--max-points", type=int, default=MAX_POINTS,
                        help=f"thin larger clouds on a voxel grid to about this many points (0: never; default {MAX_POINTS})")
    parser.add_argument("--alpha-factor", type=float, default=ALPHA_FACTOR,
                        help=f"alpha as a multiple of the median point spacing (default {ALPHA_FACTOR})")
    parser.add_argument("--faces", type=int, default=0,
                        help="at most about this many faces: the mesh made at --max-points is decimated "
                             "(error-bounded edge collapse; default: as many as --max-points gives)")
    parser.add_argument("--no-refine", action="store_true",
                        help="keep the raw alpha-shape surface (no edge flips or vertex smoothing)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def cli_main(args) -> int:
    src = Path(args.cloud)
    out = Path(args.output) if args.output else src.with_name(src.stem + "_mesh.ply")
    if args.alpha_factor <= 0:
        raise CliError(f"--alpha-factor must be positive, got {args.alpha_factor}")
    if args.max_points < 0:
        raise CliError(f"--max-points must be 0 or more, got {args.max_points}")
    if args.faces < 0:
        raise CliError(f"--faces must be 0 or more, got {args.faces}")
    ensure_not_input(out, [src])
    if out.suffix.lower() not in MESH_SUFFIXES:
        raise CliError(f"{out}: unknown mesh format {out.suffix or '(no extension)'!r}; use .ply, .stl, .obj, .off or .glb")
    t0 = time.perf_counter()
    cloud = read_point_cloud(src)
    result = mesh_for_matching(cloud.points, max_points=args.max_points or None, faces=args.faces or None,
                               alpha_factor=args.alpha_factor, refine=not args.no_refine, progress=not args.quiet,
                               label=str(src))
    vertices, faces = result.vertices, result.faces
    write_mesh(out, vertices, faces)
    for n in cloud.notes + result.notes:
        print(f"note: {n}", file=sys.stderr)
    print(f"{out}: {len(vertices)} vertices, {len(faces)} faces from {result.n_input} points "
          f"(spacing {result.spacing:.4g}, alpha {result.alpha:.4g}, {result.coverage:.0%} of points on the surface) "
          f"in {time.perf_counter() - t0:.1f} s")
    return 0
