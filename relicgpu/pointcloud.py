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

import dataclasses
import io as _stdio
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .io import Fragment, FragmentError, fragment_from_arrays

MIN_POINTS = 20
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
# Refinement (step 7): unit normals of the cloud from this many nearest points; rounds of
# edge flips; the vertex move's neighbourhood (edge steps) and its pull to the old position.
NORMAL_NEIGHBOURS = 16
FLIP_ROUNDS = 12
FLIP_MARGIN = 1e-3
SMOOTH_RINGS = 2
SMOOTH_STAY = 0.2
# load_fragment thins a cloud to this many points before meshing: the density (about 20k
# faces per fragment) at which the matcher's segmentation was measured to work (see
# tests/test_pointcloud.py); `relicgpu mesh` keeps MAX_POINTS.
MATCH_POINTS = 12_000


@dataclass(frozen=True)
class PointCloud:
    """Scanned points with optional per-point normals (unit vectors)."""
    points: np.ndarray  # (N,3) float64
    normals: np.ndarray | None  # (N,3) float64 or None
    source: str
    notes: tuple[str, ...] = ()


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


# --- point-cloud fragments (matched on their points) -----------------------

# Local fits over this many nearest points: surface variation (fracture likelihood), and
# normals (fewer: on 2,500 points of a thin vase wall 16 reach across the wall).
CLOUD_NEIGHBOURS = 16
CLOUD_NORMAL_NEIGHBOURS = 12
# Fracture likelihood: roughness is this quantile of the angles to the neighbours' normals; it is
# smoothed with weights |n_i . n_j| ** ROUGH_PARALLEL_POWER; a point is rough (fracture) when it
# lies ROUGH_SPREADS robust spreads (MAD) of the cloud's own above their median.
ROUGH_QUANTILE = 0.35
ROUGH_PARALLEL_POWER = 4
ROUGH_SPREADS = 1.0
# Outward orientation (`orient_normals`): VIEW_DIRECTIONS orthographic views from around the cloud,
# each a depth buffer over pixels one point spacing wide into which every point is splatted as a
# disc of SPLAT_PIXELS pixels (closing the gaps of a sparse wall, so nothing is seen through it); a
# point is seen where it lies within SEEN_DEPTH spacings of the nearest depth at its pixel. Then
# VOTE_ROUNDS of averaging along the surface, over links straying from the tangent planes less than
# LINK_OFFSET spacings (`_smooth_links`). Flipped normals, mean over the pieces of 24 synthetic pairs
# / 12 corpus pairs / 9 bowl-shaped shells 1-4 spacings thick (2,500-6,400 points): hidden-point
# removal and no offset limit 1.3% / 3.2% / 17%; these 1.2% / 1.8% / 5.5%.
VIEW_DIRECTIONS = 48
SPLAT_PIXELS = 3.0
SEEN_DEPTH = 1.0
VOTE_ROUNDS = 4
LINK_OFFSET = 0.5


@dataclass(frozen=True, eq=False)
class CloudFragment(Fragment):
    """A fragment given as points (no faces), matched on its points: a scan that does not close
    into a solid (sparse, thin, open). `faces` is an empty (0,3) array."""
    normals: np.ndarray | None = None  # (V,3) outward unit normals, or None where the scan had none

    def transformed(self, matrix: np.ndarray) -> "CloudFragment":
        m = np.asarray(matrix, np.float64)
        normals = None if self.normals is None else self.normals @ m[:3, :3].T
        return dataclasses.replace(self, vertices=self.vertices @ m[:3, :3].T + m[:3, 3], normals=normals)


def cloud_fragment(name: str, points, normals=None, source: str | None = None,
                   notes: tuple[str, ...] = ()) -> CloudFragment:
    """A checked CloudFragment from (N,3) points and optional (N,3) normals (made unit length)."""
    label = source or name
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise FragmentError(f"{label}: points must be an (N, 3) array, got shape {pts.shape}")
    _check_points(pts, label)
    if normals is not None:
        normals = np.asarray(normals, np.float64)
        if normals.shape != pts.shape:
            raise FragmentError(f"{label}: {len(normals)} normals for {len(pts)} points")
        length = np.linalg.norm(normals, axis=1)
        normals = normals / np.where(length > 0, length, 1.0)[:, None]
    return CloudFragment(name, pts, np.zeros((0, 3), np.int32), source, tuple(notes), normals)


def local_pca(points: np.ndarray, k: int = CLOUD_NEIGHBOURS) -> tuple[np.ndarray, np.ndarray]:
    """Principal axes of every point's k nearest points (itself included).

    Returns
    -------
    values : (N, 3) eigenvalues of the neighbourhood covariance, ascending
    vectors : (N, 3, 3) the matching unit eigenvectors as columns (vectors[:, :, 0]: the normal)
    """
    from scipy.spatial import cKDTree

    k = min(k, len(points))
    _, idx = cKDTree(points).query(points, k=k)
    q = points[idx.reshape(len(points), k)]
    d = q - q.mean(axis=1, keepdims=True)
    return np.linalg.eigh(np.einsum("nki,nkj->nij", d, d) / k)


def orient_normals(points: np.ndarray, normals: np.ndarray, k: int = CLOUD_NORMAL_NEIGHBOURS) -> np.ndarray:
    """Unoriented (N,3) normals turned outward, by visibility from outside.

    Each point votes for the side it is seen from (`visibility_votes`: depth buffers of views from
    around the cloud); the votes are then averaged a few rounds over links between
    near-parallel neighbours that do not cross a thin wall (`_smooth_links`), each neighbour's
    vote carried over with the sign that makes its normal agree with the point's. Points seen
    from no viewpoint (deep in a concavity) take their neighbours' side. Orientation from
    visibility needs no closed surface: it holds on open shells and on both faces of a thin
    wall, where the side on which the cloud is empty does not tell outside from inside.
    """
    i, j, agree = _smooth_links(points, normals, k)
    vote = visibility_votes(points, normals)
    scale = np.median(np.abs(vote[vote != 0])) if np.any(vote != 0) else 1.0
    vote = np.clip(vote / scale, -1.0, 1.0)
    n = len(points)
    from scipy.sparse import coo_matrix

    links = coo_matrix((np.concatenate([agree, agree]), (np.concatenate([i, j]), np.concatenate([j, i]))),
                       shape=(n, n)).tocsr()
    degree = np.maximum(np.asarray(abs(links).sum(axis=1)).ravel(), 1.0)
    for _ in range(VOTE_ROUNDS):
        vote = 0.5 * vote + 0.5 * (links @ vote) / degree
    return np.array(normals, np.float64) * np.where(vote < 0, -1.0, 1.0)[:, None]


def _smooth_links(points: np.ndarray, normals: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Links (i, j) between k-nearest neighbours on one smooth sheet: near-parallel normals
    (not across a crease) and a link running along the surface (not across a thin wall, whose
    two faces have parallel normals too): at a shallow angle to both tangent planes and straying
    from them less than LINK_OFFSET point spacings (a wall one or two spacings thick has
    neighbours across it at shallow angles). Returns i, j and the sign (+1/-1) of n_i . n_j."""
    from scipy.spatial import cKDTree

    n = len(points)
    dist, idx = cKDTree(points).query(points, k=min(k + 1, n))
    spacing = float(np.median(dist[:, 1])) if idx.shape[1] > 1 else 0.0
    rows = np.repeat(np.arange(n), idx.shape[1] - 1)
    pairs = np.unique(np.sort(np.stack([rows, idx[:, 1:].ravel()], 1), axis=1), axis=0)
    i, j = pairs[:, 0], pairs[:, 1]
    d = points[j] - points[i]
    length = np.maximum(np.linalg.norm(d, axis=1), 1e-300)
    dot = np.einsum("ij,ij->i", normals[i], normals[j])
    offset = np.maximum(np.abs(np.einsum("ij,ij->i", d, normals[i])), np.abs(np.einsum("ij,ij->i", d, normals[j])))
    keep = (np.abs(dot) > 0.7) & (offset < 0.5 * length) & (offset < LINK_OFFSET * spacing)
    return i[keep], j[keep], np.sign(dot[keep])


def view_directions(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    t = np.arange(n) + 0.5
    polar, turn = np.arccos(1.0 - 2.0 * t / n), np.pi * (1.0 + 5 ** 0.5) * t
    return np.stack([np.cos(turn) * np.sin(polar), np.sin(turn) * np.sin(polar), np.cos(polar)], 1)


def visibility_votes(points: np.ndarray, normals: np.ndarray, views: int = VIEW_DIRECTIONS) -> np.ndarray:
    """(N,) sum over views from around the cloud of cos(normal, direction to the viewer), over
    the views that see the point. Each view is orthographic: a depth buffer of pixels one point
    spacing wide, every point splatted into it as a disc of SPLAT_PIXELS pixels, so that a sparse
    wall hides what lies behind it (hidden-point removal, as Katz et al. 2007 do with a spherical
    flip, saw inner walls through outer ones: 13% of a thin vase piece's normals turned inward).
    Positive: the normal points outward."""
    if len(points) < 2:
        return np.zeros(len(points))
    spacing = _median_spacing(points) or 1.0
    reach = int(np.ceil(SPLAT_PIXELS))
    disc = [(du, dv) for du in range(-reach, reach + 1) for dv in range(-reach, reach + 1)
            if du * du + dv * dv <= SPLAT_PIXELS ** 2]
    rel = points - points.mean(axis=0)
    vote = np.zeros(len(points))
    for direction in view_directions(views):
        u = np.cross(direction, [1.0, 0.0, 0.0] if abs(direction[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(direction, u)
        depth = -(rel @ direction)  # from a viewer far out along `direction`: smaller is nearer
        iu, iv = (np.floor(rel @ axis / spacing).astype(np.int64) for axis in (u, v))
        iu, iv = iu - iu.min() + reach, iv - iv.min() + reach
        height = int(iv.max()) + reach + 1
        nearest = np.full((int(iu.max()) + reach + 1) * height, np.inf)
        for du, dv in disc:
            np.minimum.at(nearest, (iu + du) * height + iv + dv, depth)
        seen = depth <= nearest[iu * height + iv] + SEEN_DEPTH * spacing
        vote[seen] += normals[seen] @ direction
    return vote


def estimate_normals(points: np.ndarray, given: np.ndarray | None = None, k: int = CLOUD_NORMAL_NEIGHBOURS,
                     ) -> np.ndarray:
    """(N,3) outward unit normals of a cloud: the given ones, else local plane fits, oriented."""
    if given is not None:
        return given
    return orient_normals(points, local_pca(points, k)[1][:, :, 0], k)


def fracture_likelihood(points: np.ndarray, normals: np.ndarray, k: int = CLOUD_NORMAL_NEIGHBOURS,
                        spreads: float | None = None) -> np.ndarray:
    """Likelihood that each point lies on fracture surface, from the roughness of its normals.

    Roughness is a low quantile (ROUGH_QUANTILE) of the angles between a point's normal and
    those of its k nearest points, taken unsigned (a thin wall's other face, or a normal
    oriented the wrong way, is no roughness). On smooth skin most neighbours are near parallel;
    a skin point beside a crease (a rim, a thin wall's broken edge) still has its own side's
    neighbours, so a low quantile stays low there; on a rough break even the most parallel
    neighbours differ. The values are then smoothed twice over each neighbourhood, every
    neighbour weighted by how parallel its normal is to the point's (a bilateral filter): the
    average follows a point's own surface and does not blur fracture across a crease. The split
    between smooth and rough lies above the bulk's spread (median + ROUGH_SPREADS robust spreads
    of the log roughness, at least Otsu's split); the likelihood is a logistic of the distance
    from it.

    Parameters
    ----------
    points : (N, 3) array
    normals : (N, 3) unit normals (orientation is not used)
    k : neighbours per point
    spreads : the split's distance above the median in robust spreads (None: ROUGH_SPREADS)

    Returns
    -------
    (N,) array in [0, 1]
    """
    from scipy.spatial import cKDTree

    from .segment import otsu_split

    k = min(k, len(points))
    _, idx = cKDTree(points).query(points, k=k)
    idx = idx.reshape(len(points), k)
    parallel = np.abs(np.einsum("nkd,nd->nk", normals[idx], normals))
    angles = np.arccos(np.clip(parallel[:, 1:], 0.0, 1.0)) if k > 1 else np.zeros((len(points), 1))
    x = np.log(np.maximum(np.quantile(angles, ROUGH_QUANTILE, axis=1), 1e-6))
    weight = parallel ** ROUGH_PARALLEL_POWER
    for _ in range(2):
        x = (weight * x[idx]).sum(axis=1) / weight.sum(axis=1)
    # the smooth surface is most of a piece: the split lies above the bulk's own spread
    centre = np.median(x)
    noise = 1.4826 * np.median(np.abs(x - centre)) or 1.0
    spreads = ROUGH_SPREADS if spreads is None else spreads
    split = max(otsu_split(x, np.ones(len(x))), centre + spreads * noise)
    return 1.0 / (1.0 + np.exp(-(x - split) / noise))


# --- readers -------------------------------------------------------------

def read_point_cloud(path) -> PointCloud:
    """Read .xyz/.asc/.txt, .pcd, .ply (vertices only), .npy or .las/.laz (`io.read_las`) into a
    checked PointCloud."""
    p = Path(path)
    label = str(p)
    if not p.exists():
        raise FragmentError(f"{label}: no such file")
    if p.is_dir():
        raise FragmentError(f"{label}: is a directory, not a point-cloud file")
    suffix = p.suffix.lower()
    if suffix in (".xyz", ".asc", ".txt"):
        pts, nrm, notes = _read_text(p, label)
    elif suffix == ".pcd":
        pts, nrm, notes = _read_pcd(p, label)
    elif suffix == ".ply":
        pts, nrm, notes = _read_ply(p, label)
    elif suffix == ".npy":
        pts, nrm, notes = _read_npy(p, label)
    elif suffix in (".las", ".laz"):
        from .io import read_las
        pts, nrm, notes = read_las(p, label)
    else:
        raise FragmentError(f"{label}: unknown point-cloud format {suffix or '(no extension)'!r}; "
                            "use .xyz, .asc, .txt, .pcd, .ply, .npy, .las or .laz")
    _check_points(pts, label)
    if nrm is not None and not np.isfinite(nrm).all():
        nrm = None
        notes.append(f"{label}: normals hold NaN or infinite values; ignored")
    return PointCloud(pts, nrm, label, tuple(notes))


def _check_points(pts: np.ndarray, label: str, row_to_line=None) -> None:
    if len(pts) < MIN_POINTS:
        raise FragmentError(f"{label}: too few points ({len(pts)}); a fragment scan needs at least {MIN_POINTS}")
    bad = ~np.isfinite(pts).all(axis=1)
    if bad.any():
        first = int(np.argmax(bad))
        where = f"line {row_to_line(first)}" if row_to_line else f"point {first}"
        raise FragmentError(f"{label}: {int(bad.sum())} points have NaN or infinite coordinates (first at {where})")


def _split_normals(arr: np.ndarray, label: str, notes: list) -> tuple[np.ndarray, np.ndarray | None]:
    pts = np.ascontiguousarray(arr[:, :3], np.float64)
    if arr.shape[1] == 3:
        return pts, None
    nrm = np.asarray(arr[:, 3:6], np.float64)
    with np.errstate(invalid="ignore"):
        lengths = np.linalg.norm(nrm, axis=1)
    if np.isfinite(lengths).all() and np.all(np.abs(lengths - 1.0) < 0.05):
        return pts, np.ascontiguousarray(nrm)
    notes.append(f"{label}: columns 4 to 6 are not unit normals (colours?); ignored")
    return pts, None


_COMMENTS = ("#", "//")


def _data_lines(lines, first_line_no: int = 1):
    """(line number, fields) of each non-empty, non-comment line."""
    for no, raw in enumerate(lines, first_line_no):
        line = raw.strip()
        if not line or line.startswith(_COMMENTS):
            continue
        for c in _COMMENTS:
            line = line.split(c, 1)[0]
        yield no, line.replace(",", " ").split()


def _diagnose_table(lines, label: str, first_line_no: int, allowed: tuple[int, ...], what: str) -> FragmentError:
    """The first fault of a numeric table, named with its line number."""
    expected = None
    for no, fields in _data_lines(lines, first_line_no):
        if expected is None:
            if len(fields) not in allowed:
                return FragmentError(f"{label}: line {no} has {len(fields)} columns; expected {what}")
            expected = len(fields)
        elif len(fields) != expected:
            return FragmentError(f"{label}: line {no} has {len(fields)} columns, earlier lines have {expected}")
        for i, tok in enumerate(fields, 1):
            try:
                float(tok)
            except ValueError:
                return FragmentError(f"{label}: line {no}, column {i}: {tok[:40]!r} is not a number")
    return FragmentError(f"{label}: unreadable numeric table")


def _row_to_line(lines, first_line_no: int):
    def find(row: int) -> int:
        for k, (no, _) in enumerate(_data_lines(lines, first_line_no)):
            if k == row:
                return no
        return -1
    return find


def _parse_table(text: str, label: str, first_line_no: int, allowed: tuple[int, ...], what: str) -> np.ndarray:
    """Parse whitespace- or comma-separated numbers; fast path numpy, slow path for the error message."""
    first = next(_data_lines(text.splitlines()[:10000], first_line_no), None)
    if first is None:
        raise FragmentError(f"{label}: no points (the file has no data lines)")
    # numpy counts only data rows; on any fault re-scan the lines to name the real line.
    delimiter = "," if "," in text[: 1 << 16] else None
    try:
        arr = np.loadtxt(_stdio.StringIO(text), comments=_COMMENTS, delimiter=delimiter, ndmin=2, dtype=np.float64)
    except ValueError:
        raise _diagnose_table(text.splitlines(), label, first_line_no, allowed, what) from None
    if arr.shape[1] not in allowed:
        raise _diagnose_table(text.splitlines(), label, first_line_no, allowed, what)
    return arr


def _read_text(p: Path, label: str):
    text = p.read_bytes().decode("latin-1")
    arr = _parse_table(text, label, 1, (3, 6), "3 (x y z) or 6 (x y z nx ny nz)")
    notes: list[str] = []
    pts, nrm = _split_normals(arr, label, notes)
    if not np.isfinite(pts).all():
        _check_points(pts, label, _row_to_line(text.splitlines(), 1))
    return pts, nrm, notes


# PCD: https://pointclouds.org/documentation/tutorials/pcd_file_format.html
_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
              ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}


def _read_pcd(p: Path, label: str):
    raw = p.read_bytes()
    header: dict[str, list[str]] = {}
    pos = 0
    line_no = 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise FragmentError(f"{label}: PCD header has no DATA line")
        line_no += 1
        line = raw[pos:end].decode("latin-1").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        header[key.upper()] = vals
        if key.upper() == "DATA":
            break
        if line_no > 100:
            raise FragmentError(f"{label}: not a PCD file (no DATA line in the first 100 lines)")
    for key in ("FIELDS", "SIZE", "TYPE"):
        if key not in header:
            raise FragmentError(f"{label}: PCD header lacks the {key} line")
    fields, sizes, types = header["FIELDS"], header["SIZE"], header["TYPE"]
    counts = header.get("COUNT", ["1"] * len(fields))
    if not (len(fields) == len(sizes) == len(types) == len(counts)):
        raise FragmentError(f"{label}: PCD header lists {len(fields)} FIELDS but {len(sizes)} SIZE, "
                            f"{len(types)} TYPE and {len(counts)} COUNT entries")
    for axis in "xyz":
        if axis not in fields:
            raise FragmentError(f"{label}: PCD has no {axis!r} field (fields: {' '.join(fields)})")
    try:
        sizes_i = [int(s) for s in sizes]
        counts_i = [int(c) for c in counts]
        width = int(header.get("WIDTH", ["0"])[0])
        height = int(header.get("HEIGHT", ["1"])[0])
        n_points = int(header.get("POINTS", [str(width * height)])[0])
    except ValueError as exc:
        raise FragmentError(f"{label}: PCD header has a non-integer SIZE/COUNT/WIDTH/HEIGHT/POINTS ({exc})") from None
    dtypes = []
    for name, t, s, c in zip(fields, types, sizes_i, counts_i):
        code = _PCD_TYPES.get((t.upper(), s))
        if code is None:
            raise FragmentError(f"{label}: PCD field {name!r} has unsupported TYPE {t} with SIZE {s}")
        dtypes.append((name, "<" + code, (c,)) if c != 1 else (name, "<" + code))
    mode = (header["DATA"] or [""])[0].lower()
    organised = height > 1
    notes: list[str] = []
    if mode == "ascii":
        text = raw[pos:].decode("latin-1")
        ncols = sum(counts_i)
        arr = _parse_table(text, label, line_no + 1, (ncols,), f"{ncols} (the PCD FIELDS with their COUNT)")
        if len(arr) != n_points:
            notes.append(f"{label}: header declares {n_points} points, data holds {len(arr)}")
        offsets = np.cumsum([0] + counts_i)
        col = {name: offsets[i] for i, name in enumerate(fields)}
        table = arr
        row_to_line = _row_to_line(text.splitlines(), line_no + 1)
    elif mode == "binary":
        dt = np.dtype(dtypes)
        need = n_points * dt.itemsize
        have = len(raw) - pos
        if have < need:
            raise FragmentError(f"{label}: truncated binary PCD: header declares {n_points} points of "
                                f"{dt.itemsize} bytes ({need} bytes), the file holds {have} bytes of data")
        rec = np.frombuffer(raw, dt, count=n_points, offset=pos)
        table = np.column_stack([rec[a].astype(np.float64) for a in ("x", "y", "z")]
                                + ([rec[a].astype(np.float64) for a in ("normal_x", "normal_y", "normal_z")]
                                   if all(a in fields for a in ("normal_x", "normal_y", "normal_z")) else []))
        col = {name: i for i, name in enumerate(["x", "y", "z", "normal_x", "normal_y", "normal_z"])}
        row_to_line = None
    elif mode == "binary_compressed":
        raise FragmentError(f"{label}: PCD 'DATA binary_compressed' is unsupported; "
                            "save the cloud as binary or ascii PCD (e.g. pcl_convert_pcd_ascii_binary)")
    else:
        raise FragmentError(f"{label}: unknown PCD DATA mode {mode!r}; expected ascii or binary")
    pts = np.column_stack([table[:, col[a]] for a in "xyz"]).astype(np.float64)
    nrm = None
    if all(a in col and a in fields for a in ("normal_x", "normal_y", "normal_z")):
        nrm = np.column_stack([table[:, col[a]] for a in ("normal_x", "normal_y", "normal_z")]).astype(np.float64)
    bad = ~np.isfinite(pts).all(axis=1)
    if organised and bad.any():
        # An organised cloud marks pixels without a return with NaN (PCL's is_dense=false).
        notes.append(f"{label}: dropped {int(bad.sum())} NaN points of the organised {width}x{height} cloud")
        pts = pts[~bad]
        nrm = nrm[~bad] if nrm is not None else None
    elif bad.any():
        _check_points(pts, label, row_to_line)
    return pts, nrm, notes


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def _read_ply(p: Path, label: str):
    raw = p.read_bytes()
    if not raw.startswith(b"ply"):
        raise FragmentError(f"{label}: not a PLY file (no 'ply' magic line)")
    end = raw.find(b"end_header")
    if end < 0:
        raise FragmentError(f"{label}: PLY header has no end_header line")
    body = raw.find(b"\n", end) + 1
    header_lines = raw[:body].decode("latin-1").splitlines()
    fmt = None
    elements: list[tuple[str, int, list]] = []
    for line in header_lines:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1] if len(parts) > 1 else ""
        elif parts[0] == "element" and len(parts) == 3:
            try:
                elements.append((parts[1], int(parts[2]), []))
            except ValueError:
                raise FragmentError(f"{label}: PLY element {parts[1]!r} has a non-integer count {parts[2]!r}") from None
        elif parts[0] == "property" and elements:
            elements[-1][2].append(parts[1:])
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise FragmentError(f"{label}: unknown PLY format {fmt!r}")
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise FragmentError(f"{label}: PLY has no vertex element")
    vi = names.index("vertex")
    if any(count > 0 for _, count, _ in elements[:vi]):
        raise FragmentError(f"{label}: unsupported PLY layout (elements with data before 'vertex')")
    _, n_points, props = elements[vi]
    prop_names = []
    dtypes = []
    endian = "<" if fmt == "binary_little_endian" else ">"
    for prop in props:
        if prop[0] == "list":
            raise FragmentError(f"{label}: unsupported PLY vertex property list {prop[-1]!r}")
        if len(prop) != 2 or prop[0] not in _PLY_TYPES:
            raise FragmentError(f"{label}: PLY vertex property {' '.join(prop)!r} has an unknown type")
        prop_names.append(prop[1])
        dtypes.append((prop[1], endian + _PLY_TYPES[prop[0]]))
    for axis in "xyz":
        if axis not in prop_names:
            raise FragmentError(f"{label}: PLY vertices have no {axis!r} property")
    has_normals = all(a in prop_names for a in ("nx", "ny", "nz"))
    if fmt == "ascii":
        text = raw[body:].decode("latin-1")
        lines = text.splitlines()[:n_points]
        if len(lines) < n_points:
            raise FragmentError(f"{label}: truncated PLY: header declares {n_points} vertices, the file has {len(lines)} lines after the header")
        ncols = len(prop_names)
        arr = _parse_table("\n".join(lines), label, len(header_lines) + 1, (ncols,), f"{ncols} (the PLY vertex properties)")
        if len(arr) < n_points:
            raise FragmentError(f"{label}: truncated PLY: header declares {n_points} vertices, found {len(arr)}")
        table = {name: arr[:, i] for i, name in enumerate(prop_names)}
        row_to_line = _row_to_line(lines, len(header_lines) + 1)
    else:
        dt = np.dtype(dtypes)
        need = n_points * dt.itemsize
        have = len(raw) - body
        if have < need:
            raise FragmentError(f"{label}: truncated binary PLY: header declares {n_points} vertices of "
                                f"{dt.itemsize} bytes ({need} bytes), the file holds {have} bytes of data")
        rec = np.frombuffer(raw, dt, count=n_points, offset=body)
        table = {name: rec[name] for name in prop_names}
        row_to_line = None
    pts = np.column_stack([table[a] for a in "xyz"]).astype(np.float64)
    nrm = np.column_stack([table[a] for a in ("nx", "ny", "nz")]).astype(np.float64) if has_normals else None
    notes: list[str] = []
    if any(name == "face" and count > 0 for name, count, _ in elements):
        notes.append(f"{label}: the PLY's faces were ignored; its vertices were triangulated afresh")
    if not np.isfinite(pts).all():
        _check_points(pts, label, row_to_line)
    return pts, nrm, notes


def _read_npy(p: Path, label: str):
    try:
        arr = np.load(p, allow_pickle=False)
    except (ValueError, EOFError, OSError) as exc:
        raise FragmentError(f"{label}: unreadable or truncated .npy file ({exc})") from None
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "fiu":
        raise FragmentError(f"{label}: .npy must hold a numeric array, got dtype {getattr(arr, 'dtype', type(arr))}")
    if arr.ndim != 2 or arr.shape[1] not in (3, 6):
        raise FragmentError(f"{label}: .npy array has shape {arr.shape}; expected (N, 3) points or (N, 6) points with normals")
    notes: list[str] = []
    pts, nrm = _split_normals(arr, label, notes)
    return pts, nrm, notes


# --- triangulation -------------------------------------------------------

def voxel_thin(points: np.ndarray, voxel: float) -> np.ndarray:
    """One point per occupied voxel of edge `voxel`: the mean of the points in it."""
    keys, _ = _voxel_keys(points, points.min(0), voxel)
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    out = np.empty((len(counts), 3))
    for axis in range(3):
        out[:, axis] = np.bincount(inverse, points[:, axis], minlength=len(counts)) / counts
    return out


def _voxel_keys(points: np.ndarray, lo: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """(N,) voxel key and (N,3) integer cell of every point on a grid of edge `voxel` from `lo`."""
    cells = np.floor((points - lo) / voxel).astype(np.int64)
    dims = cells.max(0) + 1
    return (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2], cells


def _occupied_voxels(points: np.ndarray, lo: np.ndarray, voxel: float) -> int:
    keys = np.sort(_voxel_keys(points, lo, voxel)[0])
    return int(np.count_nonzero(np.diff(keys)) + 1)


def even_subsample(points: np.ndarray, n: int) -> np.ndarray:
    """Indices (sorted) of at most n points spread evenly over space: on the finest voxel grid
    with at most n occupied voxels (anchored at the bounding box), the point nearest each
    voxel's centre.

    Unlike a random choice it depends on the points only through their shape: the same up to
    scale and translation (units), and a few points more or fewer change only their own voxels.

    Parameters
    ----------
    points : (N, 3) array
    n : int

    Returns
    -------
    (M,) int64 array, M <= n (all of arange(N) when N <= n)
    """
    points = np.asarray(points, np.float64)
    if len(points) <= n:
        return np.arange(len(points))
    if n <= 0:
        return np.zeros(0, np.int64)
    lo = points.min(0)
    voxel = choose_voxel(points, n)
    keys, cells = _voxel_keys(points, lo, voxel)
    off_centre = np.linalg.norm(points - lo - (cells + 0.5) * voxel, axis=1)
    order = np.lexsort((np.arange(len(points)), off_centre, keys))
    first = np.concatenate([[True], keys[order][1:] != keys[order][:-1]])
    return np.sort(order[first])


def choose_voxel(points: np.ndarray, max_points: int) -> float:
    """The smallest voxel edge (within 5%) that leaves at most max_points occupied voxels."""
    lo = points.min(0)
    diag = float(np.linalg.norm(points.max(0) - lo))
    # Bisect on log(voxel): the count of occupied voxels falls as they grow.
    small, big = diag * 1e-6, diag
    for _ in range(40):
        mid = np.sqrt(small * big)
        if _occupied_voxels(points, lo, mid) > max_points:
            small = mid
        else:
            big = mid
        if big / small < 1.05:
            break
    return big


def _tet_geometry(q: np.ndarray, simplices: np.ndarray, chunk: int = 500_000):
    """Per tetrahedron: circumradius of the face opposite each vertex (T,4), six times the
    signed volume, and the longest edge."""
    n = len(simplices)
    face_radius = np.empty((n, 4))
    volume6 = np.empty(n)
    longest = np.empty(n)
    for s in range(0, n, chunk):
        p = q[simplices[s:s + chunk]]  # (t,4,3)
        edges = {(i, j): p[:, j] - p[:, i] for i in range(4) for j in range(i + 1, 4)}
        sq = {key: np.einsum("ij,ij->i", e, e) for key, e in edges.items()}
        longest[s:s + chunk] = np.sqrt(np.max(np.stack(list(sq.values())), axis=0))
        volume6[s:s + chunk] = np.einsum("ij,ij->i", np.cross(edges[0, 1], edges[0, 2]), edges[0, 3])
        for k in range(4):
            i, j, m = (v for v in range(4) if v != k)
            cross = np.cross(edges[i, j], edges[i, m])
            area2 = np.sqrt(np.einsum("ij,ij->i", cross, cross))  # twice the area
            with np.errstate(divide="ignore", invalid="ignore"):
                r = np.sqrt(sq[i, j] * sq[i, m] * sq[j, m]) / (2.0 * area2)
            face_radius[s:s + chunk, k] = np.where(area2 > 0, r, np.inf)
    return face_radius, volume6, longest


# Faces of a positively oriented tetrahedron (v0..v3), wound outwards; row k is opposite vertex k.
_OUT_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


class _Tets:
    """The Delaunay tetrahedralisation with the arrays the carving needs."""

    def __init__(self, q: np.ndarray):
        from scipy.spatial import Delaunay
        from scipy.spatial import QhullError

        # A jitter of 1e-9 (q spans [-1, 1]) breaks exact coplanarity, as of points
        # sampled from flat faces, which makes Qhull merge facets for minutes.
        q = q + np.random.default_rng(0).uniform(-1e-9, 1e-9, q.shape)
        try:
            tri = Delaunay(q, qhull_options="Qbb Qz Q12")
        except QhullError as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
            raise FragmentError(f"the points span no volume (flat or collinear?): Qhull says {first}") from None
        self.q = q
        self.simplices = tri.simplices.astype(np.int64)
        self.neighbors = tri.neighbors.astype(np.int64)
        self.n_points = len(q)
        self.face_radius, self.volume6, self.longest = _tet_geometry(q, self.simplices)

    def edge_keys(self, which: np.ndarray) -> np.ndarray:
        """(len(which),6) keys (lo * n + hi) of the edges of the given tetrahedra, in the order of _TET_EDGES."""
        s = self.simplices[which]
        lo = np.stack([np.minimum(s[:, i], s[:, j]) for i, j in _TET_EDGES], 1)
        hi = np.stack([np.maximum(s[:, i], s[:, j]) for i, j in _TET_EDGES], 1)
        return lo * self.n_points + hi


def _outside_by_flood(tets: _Tets, alpha: float) -> np.ndarray:
    """Tetrahedra reached from infinity through faces of circumradius above alpha."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(tets.simplices)
    passable = tets.face_radius > alpha
    t, k = np.nonzero(passable)
    other = tets.neighbors[t, k]
    other = np.where(other < 0, n, other)  # node n is the outside of the convex hull
    graph = coo_matrix((np.ones(len(t), np.int8), (t, other)), shape=(n + 1, n + 1))
    _, labels = connected_components(graph, directed=False)
    return labels[:n] == labels[n]


def _largest_body(tets: _Tets, inside: np.ndarray) -> tuple[np.ndarray, int, float]:
    """Keep the largest face-connected set of inside tetrahedra (by volume).

    Returns the kept set, the number of bodies and the kept share of the inside volume.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(inside)
    idx = np.nonzero(inside)[0]
    if len(idx) == 0:
        return inside, 0, 0.0
    nb = tets.neighbors
    t, k = np.nonzero(inside[:, None] & (nb >= 0))
    other = nb[t, k]
    keep = inside[other]
    graph = coo_matrix((np.ones(int(keep.sum()), np.int8), (t[keep], other[keep])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    body, body_of = np.unique(labels[idx], return_inverse=True)
    vol = np.bincount(body_of, np.abs(tets.volume6[idx]))
    best = int(np.argmax(vol))
    out = np.zeros(n, bool)
    out[idx[body_of == best]] = True
    total = float(vol.sum())
    return out, len(body), float(vol[best] / total) if total > 0 else 1.0


def _boundary(tets: _Tets, inside: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boundary triangles of the inside tetrahedra, wound outwards, and the tetrahedron of each."""
    nb = tets.neighbors
    nb_inside = np.where(nb >= 0, inside[np.maximum(nb, 0)], False)
    t, k = np.nonzero(inside[:, None] & ~nb_inside)
    order = _OUT_FACES[k]
    negative = tets.volume6[t] < 0
    order[negative] = order[negative][:, [0, 2, 1]]
    faces = np.take_along_axis(tets.simplices[t], order, axis=1)
    return faces, t


# Edges of a tetrahedron (local vertex pairs, the order of _Tets.edge_keys) and the two other vertices.
_TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
_TET_EDGE_OTHERS = np.array([[2, 3], [1, 3], [1, 2], [0, 3], [0, 2], [0, 1]])


@dataclass
class _Surface:
    """The boundary of the inside tetrahedra, made a combinatorial 2-manifold by splitting pinches."""
    faces: np.ndarray  # (F,3) indices into `source`
    source: np.ndarray  # (V,) point index of each (possibly duplicated) vertex
    bad_edges: np.ndarray  # keys of edges shared by more than two faces before splitting
    bad_vertices: np.ndarray  # points whose faces formed more than one fan
    component: np.ndarray  # (F,) edge-connected component of each face
    inconsistent: int  # paired edges run the same way in both faces (wrong winding)
    closed: bool  # every edge of `faces` has exactly two faces


def _pair_incidences(tets: _Tets, inside: np.ndarray, faces: np.ndarray, face_tet: np.ndarray):
    """Pair the two faces meeting at each edge; at an edge with more faces, pair the two faces
    that bound the same run of inside tetrahedra around it."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nf, n = len(faces), tets.n_points
    a = faces.T.ravel()  # incidence i = slot * nf + face: the edge from corner slot to slot+1
    b = np.roll(faces, -1, axis=1).T.ravel()
    keys = np.minimum(a, b) * n + np.maximum(a, b)
    uniq, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    group = inverse.astype(np.int64)
    bad = counts[inverse] > 2
    bad_keys = uniq[counts > 2]
    if bad.any():
        n_tets = len(tets.simplices)
        ends = np.zeros(n, bool)
        ends[bad_keys // n] = True
        ends[bad_keys % n] = True
        maybe = np.nonzero(inside & (ends[tets.simplices].sum(axis=1) >= 2))[0]
        maybe_keys = tets.edge_keys(maybe)
        tt, ss = np.nonzero(np.isin(maybe_keys, bad_keys))
        e_idx = np.searchsorted(bad_keys, maybe_keys[tt, ss])
        tt = maybe[tt]
        node_keys = np.unique(e_idx * n_tets + tt)
        rows, cols = [], []
        for c in (0, 1):
            other = tets.neighbors[tt, _TET_EDGE_OTHERS[ss, c]]
            ok = other >= 0
            ok[ok] = inside[other[ok]]
            rows.append(np.searchsorted(node_keys, e_idx[ok] * n_tets + tt[ok]))
            cols.append(np.searchsorted(node_keys, e_idx[ok] * n_tets + other[ok]))
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(len(node_keys),) * 2)
        _, run = connected_components(graph, directed=False)
        inc = np.nonzero(bad)[0]
        e_of = np.searchsorted(bad_keys, keys[inc])
        node = np.searchsorted(node_keys, e_of * n_tets + face_tet[inc % nf])
        group[inc] = len(uniq) + run[node]
    order = np.argsort(group, kind="stable")
    first, second = order[0::2], order[1::2]
    if len(order) % 2 or not np.array_equal(group[first], group[second]):
        raise RuntimeError("internal error: boundary edges do not pair up")
    return first, second, bad_keys


def _links(faces: np.ndarray, first: np.ndarray, second: np.ndarray):
    """The wedges (3*face+corner) that each pair of faces joins at either end of its edge."""
    nf = len(faces)
    f1, s1 = first % nf, first // nf
    f2, s2 = second % nf, second // nf
    # The edge runs from corner s to s+1; in the other face the same vertex sits at s2 or s2+1.
    s1b, s2b = (s1 + 1) % 3, (s2 + 1) % 3
    same = faces[f1, s1] == faces[f2, s2]
    w1a, w1b = 3 * f1 + s1, 3 * f1 + s1b
    w2a = 3 * f2 + np.where(same, s2, s2b)
    w2b = 3 * f2 + np.where(same, s2b, s2)
    return w1a, w2a, w1b, w2b


def _components(rows: np.ndarray, cols: np.ndarray, n: int):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n, n))
    return connected_components(graph, directed=False)


def _fans(faces: np.ndarray, first: np.ndarray, second: np.ndarray):
    """Label each wedge (face, corner) by the fan of faces it belongs to around its vertex:
    wedges at a vertex are joined across every paired edge. Returns (labels, count)."""
    w1a, w2a, w1b, w2b = _links(faces, first, second)
    n_fans, fan = _components(np.concatenate([w1a, w1b]), np.concatenate([w2a, w2b]), 3 * len(faces))
    return fan.astype(np.int64), n_fans


def _repair_double_edges(faces: np.ndarray, first: np.ndarray, second: np.ndarray, max_rounds: int = 6):
    """Re-pair the faces of edges still shared by four (or more) faces after splitting pinched vertices.

    This happens where the faces around an end of the edge form one fan that passes
    the edge more than once. Cutting that fan at the edge gives arcs; each arc takes
    its own copy of the end and the two faces of the edge that bound it. A round
    handles one edge per vertex, so that the arcs pair up.
    """
    nf = len(faces)
    for _ in range(max_rounds):
        fan, n_fans = _fans(faces, first, second)
        new = fan.reshape(nf, 3)
        f1, s1 = first % nf, first // nf
        va, vb = new[f1, s1], new[f1, (s1 + 1) % 3]
        lo, hi = np.minimum(va, vb), np.maximum(va, vb)
        key = lo * n_fans + hi
        _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
        bad = counts[inverse] > 1
        if not bad.any():
            return first, second, fan, n_fans, True
        # One edge per vertex and round: those that come first (by key) at both of their ends.
        idx = np.nonzero(bad)[0]
        ends = np.concatenate([lo[idx], hi[idx]])
        keys2 = np.tile(key[idx], 2)
        order = np.lexsort((keys2, ends))
        head = np.r_[True, ends[order][1:] != ends[order][:-1]]
        first_at_end = np.full(n_fans, -1, np.int64)
        first_at_end[ends[order][head]] = keys2[order][head]
        chosen = bad & (first_at_end[lo] == key) & (first_at_end[hi] == key)
        # The fans of the cut ends (the lower end of each chosen edge), without the joins
        # across the chosen edges, on the small graph of those wedges only.
        is_cut = np.zeros(n_fans, bool)
        is_cut[lo[chosen]] = True
        w1a, w2a, w1b, w2b = _links(faces, first, second)
        at_a = is_cut[va] & ~chosen
        at_b = is_cut[vb] & ~chosen
        wedge_vertex = fan  # the new vertex of every wedge
        nodes = np.nonzero(is_cut[wedge_vertex])[0]
        rows = np.searchsorted(nodes, np.concatenate([w1a[at_a], w1b[at_b]]))
        cols = np.searchsorted(nodes, np.concatenate([w2a[at_a], w2b[at_b]]))
        _, arc_of_node = _components(rows, cols, len(nodes))
        inc = np.concatenate([first[chosen], second[chosen]])
        end = np.tile(lo[chosen], 2)
        f_inc = inc % nf
        corner = np.argmax(new[f_inc] == end[:, None], axis=1)
        arc = arc_of_node[np.searchsorted(nodes, 3 * f_inc + corner)]
        _, edge_no = np.unique(key[chosen], return_inverse=True)
        group = np.tile(edge_no, 2) * (3 * nf) + arc
        order = np.argsort(group, kind="stable")
        g = group[order]
        if len(g) % 2 or not np.array_equal(g[0::2], g[1::2]):
            break
        first = np.concatenate([first[~chosen], inc[order[0::2]]])
        second = np.concatenate([second[~chosen], inc[order[1::2]]])
    fan, n_fans = _fans(faces, first, second)
    return first, second, fan, n_fans, False


def _surface(tets: _Tets, inside: np.ndarray) -> _Surface:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    faces, face_tet = _boundary(tets, inside)
    nf = len(faces)
    if nf == 0:
        empty = np.zeros(0, np.int64)
        return _Surface(np.zeros((0, 3), np.int64), empty, empty, empty, empty, 0, True)
    first, second, bad_keys = _pair_incidences(tets, inside, faces, face_tet)
    first, second, fan, n_fans, closed = _repair_double_edges(faces, first, second)
    source = np.empty(n_fans, np.int64)
    source[fan] = faces.ravel()
    copies = np.bincount(source, minlength=tets.n_points)
    f1, s1, f2, s2 = first % nf, first // nf, second % nf, second // nf
    face_graph = coo_matrix((np.ones(len(f1), np.int8), (f1, f2)), shape=(nf, nf))
    _, component = connected_components(face_graph, directed=False)
    inconsistent = int(np.count_nonzero(faces[f1, s1] == faces[f2, s2]))
    return _Surface(fan.reshape(nf, 3), source, bad_keys, np.nonzero(copies > 1)[0], component,
                    inconsistent, closed)


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


def _median_spacing(q: np.ndarray) -> float:
    from scipy.spatial import cKDTree
    d, _ = cKDTree(q).query(q, k=2, workers=-1)
    nn = d[:, 1]
    nn = nn[nn > 0]
    return float(np.median(nn)) if len(nn) else 0.0


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


# --- refinement ------------------------------------------------------------

def _unit(x: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(x, axis=-1, keepdims=True)
    return x / np.where(length > 0, length, 1.0)


def _area_vectors(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Per face, the normal scaled by twice the area."""
    return np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])


def cloud_normals(vertices: np.ndarray, faces: np.ndarray, cloud: np.ndarray,
                  k: int = NORMAL_NEIGHBOURS) -> np.ndarray:
    """Unit normal at each vertex: the least principal axis of its k nearest cloud points,
    turned to agree with the mesh's area-weighted vertex normal (outwards)."""
    from scipy.spatial import cKDTree

    k = min(k, len(cloud))
    _, idx = cKDTree(cloud).query(vertices, k=k, workers=-1)
    normals = np.empty_like(vertices)
    for s in range(0, len(vertices), 200_000):
        nb = cloud[idx[s:s + 200_000]]
        nb = nb - nb.mean(axis=1, keepdims=True)
        _, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
        normals[s:s + 200_000] = vec[:, :, 0]
    mesh_normals = np.zeros_like(vertices)
    area = _area_vectors(vertices, faces)
    for c in range(3):
        for axis in range(3):
            mesh_normals[:, axis] += np.bincount(faces[:, c], area[:, axis], minlength=len(vertices))
    return normals * np.where(np.einsum("ij,ij->i", normals, mesh_normals) < 0, -1.0, 1.0)[:, None]


def _edge_pairs(faces: np.ndarray):
    """For each edge of a closed manifold: its ends (a, b) as in the first face, the vertex
    opposite in that face (c) and in the other (d), both faces, and the sorted edge keys.
    None when some edge is not shared by exactly two faces."""
    nf, n = len(faces), int(faces.max()) + 1
    a, b, c = faces.ravel(), np.roll(faces, -1, axis=1).ravel(), np.roll(faces, -2, axis=1).ravel()
    key = np.minimum(a, b) * n + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    k = key[order]
    if len(k) % 2 or not np.array_equal(k[0::2], k[1::2]) or (len(k) > 2 and (k[2::2] == k[1:-1:2]).any()):
        return None
    h1, h2 = order[0::2], order[1::2]
    face = np.arange(3 * nf) // 3
    return a[h1], b[h1], c[h1], c[h2], face[h1], face[h2], k[0::2], n


def flip_edges(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, rounds: int = FLIP_ROUNDS):
    """Flip edges where both new triangles agree better with the vertex normals than the old
    pair's worse one did (by cosine to the mean normal of their corners). Each round flips an
    independent set of edges (no face twice) whose new edge does not exist yet, so the mesh
    stays a closed manifold. Returns the new faces (None if the mesh is not a closed
    manifold) and the number of flips."""
    f = np.asarray(faces, np.int64).copy()
    v = vertices
    # a flip that leaves a triangle of (nearly) no area would have no trustworthy normal
    tiny = 1e-12 * float(np.ptp(v, axis=0).max()) ** 2
    total = 0

    def agreement(t):
        area = _area_vectors(v, t)
        cos = np.einsum("ij,ij->i", _unit(area), _unit(normals[t].sum(axis=1)))
        return np.where(np.einsum("ij,ij->i", area, area) > tiny ** 2, cos, -2.0)

    changed = np.ones(len(f), bool)  # an edge's gain depends on its two faces only
    for _ in range(rounds):
        pairs = _edge_pairs(f)
        if pairs is None:
            return None, total
        a, b, c, d, f1, f2, keys, n = pairs
        e = np.nonzero((changed[f1] | changed[f2]) & (c != d))[0]
        a, b, c, d, f1, f2 = a[e], b[e], c[e], d[e], f1[e], f2[e]
        t1, t2 = np.stack([a, d, c], 1), np.stack([d, b, c], 1)
        old = np.minimum(agreement(np.stack([a, b, c], 1)), agreement(np.stack([b, a, d], 1)))
        gain = np.minimum(agreement(t1), agreement(t2)) - old
        new_key = np.minimum(c, d) * n + np.maximum(c, d)
        cand = np.nonzero(gain > FLIP_MARGIN)[0]
        at = np.minimum(np.searchsorted(keys, new_key[cand]), len(keys) - 1)  # keys are sorted
        cand = cand[keys[at] != new_key[cand]]
        if len(cand) == 0:
            break
        changed[:] = False  # candidates that lose to a neighbour below are tried again next round
        changed[f1[cand]] = changed[f2[cand]] = True
        cand = cand[np.argsort(-gain[cand], kind="stable")]  # largest gain first
        rank = np.arange(len(cand))
        first = np.full(len(f), len(cand))
        np.minimum.at(first, np.concatenate([f1[cand], f2[cand]]), np.concatenate([rank, rank]))
        cand = cand[(first[f1[cand]] == rank) & (first[f2[cand]] == rank)]
        _, once = np.unique(new_key[cand], return_index=True)  # two flips must not make one edge
        cand = cand[np.sort(once)]
        f[f1[cand]] = t1[cand]
        f[f2[cand]] = t2[cand]
        total += len(cand)
    return f, total


def quadric_smooth(vertices: np.ndarray, faces: np.ndarray, rings: int = SMOOTH_RINGS,
                   stay: float = SMOOTH_STAY) -> np.ndarray:
    """Move each vertex to the point nearest (least squares) to the planes of the triangles
    within `rings` edge steps, weighted by area, plus `stay` times their summed weight (the
    trace of the plane quadric) pulling it to where it was. On a smooth patch this removes noise across the surface and
    barely moves along it; at a crease the planes of both sides hold it on the crease."""
    from scipy.sparse import coo_matrix

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    nv, nf = len(v), len(f)
    area_vec = _area_vectors(v, f)
    area = 0.5 * np.linalg.norm(area_vec, axis=1)
    normal = _unit(area_vec)
    centre = v[f].mean(axis=1)
    nn = np.einsum("fi,fj->fij", normal, normal) * area[:, None, None]
    q = np.concatenate([nn.reshape(nf, 9), np.einsum("fij,fj->fi", nn, centre)], axis=1)
    incidence = coo_matrix((np.ones(3 * nf), (f.ravel(), np.repeat(np.arange(nf), 3))), shape=(nv, nf)).tocsr()
    acc = incidence @ q
    if rings > 1:
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        adjacency = coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                               shape=(nv, nv)).tocsr()
        adjacency.data[:] = 1.0
        for _ in range(rings - 1):
            acc = acc + adjacency @ acc
    mat = acc[:, :9].reshape(nv, 3, 3)
    pull = stay * np.trace(mat, axis1=1, axis2=2)
    mat = mat + pull[:, None, None] * np.eye(3)
    rhs = acc[:, 9:] + pull[:, None] * v
    moved = v.copy()
    ok = pull > 0
    moved[ok] = np.linalg.solve(mat[ok], rhs[ok][:, :, None])[:, :, 0]
    return moved


def refine_surface(vertices: np.ndarray, faces: np.ndarray, cloud: np.ndarray):
    """Step 7 of the module notes: flips by the cloud's normals, one quadric smoothing, flips
    again. Returns (vertices, faces), or None when the mesh is not a closed manifold."""
    f = np.asarray(faces, np.int64)
    normals = cloud_normals(vertices, f, cloud)
    f, _ = flip_edges(vertices, f, normals)
    if f is None:
        return None
    v = quadric_smooth(vertices, f)
    f, _ = flip_edges(v, f, normals)
    if f is None:
        return None
    return v, f.astype(np.int32)


def closed_manifold_fault(vertices: np.ndarray, faces: np.ndarray) -> str | None:
    """None when the mesh is one closed, consistently wound, outward body with no degenerate
    faces and no two vertices at one place; else what is wrong."""
    from .io import count_bodies

    v, f = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    if len(f) < 4:
        return "fewer than 4 faces"
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    if (np.einsum("ij,ij->i", cross, cross) == 0).any():
        return "degenerate faces"
    d = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    key = np.sort(d[:, 0] * len(v) + d[:, 1])
    if (np.diff(key) == 0).any():
        return "an edge used twice in one direction (non-manifold or flipped)"
    if not np.isin(d[:, 1] * len(v) + d[:, 0], key).all():
        return "open edges"
    if len(np.unique(v, axis=0)) != len(v):
        return "two vertices at one place (the surface touches itself)"
    if count_bodies(v, f) != 1:
        return "more than one body"
    if np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() <= 0:
        return "wound inwards"
    return None


def load_point_cloud_fragment(path, name: str | None = None, *, max_points: int | None = MATCH_POINTS,
                              alpha_factor: float = ALPHA_FACTOR, progress: bool = False) -> Fragment:
    """Read a point-cloud file and triangulate it into a checked Fragment (called by relicgpu.io.load_fragment);
    a cloud that does not close into a solid becomes a CloudFragment, matched on its points.

    The cloud is thinned to max_points (MATCH_POINTS: the density the matcher is tuned for);
    `relicgpu mesh` makes a finer mesh to keep.
    """
    p = Path(path)
    cloud = read_point_cloud(p)
    try:
        result = triangulate(cloud.points, max_points=max_points, alpha_factor=alpha_factor,
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
                        help="aim at about this many faces by thinning the cloud to half as many points first "
                             "(default: as many as --max-points gives)")
    parser.add_argument("--no-refine", action="store_true",
                        help="keep the raw alpha-shape surface (no edge flips or vertex smoothing)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def cli_main(args) -> int:
    from .cli import CliError
    from .io import MESH_SUFFIXES, ensure_not_input, write_mesh

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
    # A closed surface has about twice as many faces as vertices.
    max_points = args.max_points or None
    if args.faces:
        max_points = min(max_points or args.faces // 2, max(args.faces // 2, MIN_POINTS))
    result = triangulate(cloud.points, max_points=max_points, alpha_factor=args.alpha_factor,
                         refine=not args.no_refine, progress=not args.quiet, label=str(src))
    vertices, faces = result.vertices, result.faces
    write_mesh(out, vertices, faces)
    for n in cloud.notes + result.notes:
        print(f"note: {n}", file=sys.stderr)
    print(f"{out}: {len(vertices)} vertices, {len(faces)} faces from {result.n_input} points "
          f"(spacing {result.spacing:.4g}, alpha {result.alpha:.4g}, {result.coverage:.0%} of points on the surface) "
          f"in {time.perf_counter() - t0:.1f} s")
    return 0
