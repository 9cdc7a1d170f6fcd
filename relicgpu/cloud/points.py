"""Point-cloud fragments, matched on their points: `CloudFragment`, normals (local PCA, oriented
outwards by visibility), the fracture likelihood of each point, and thinning (voxel grid, even
subsample)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..io.clouds import _check_points
from ..io.fragment import Fragment, FragmentError
from ..topology import otsu_split

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
# Given normals that point into the solid (a cloud exported inside out) are turned outward where
# the views from around the cloud (`visibility_votes`) see more than INWARD of their weight facing
# away. With their true normals every cloud `bench_clouds.py` makes (2,500 points: the corpus, the
# thin objects, the Blender shards, the synth shapes) reads 0.00-0.04, negated 0.97-1.00; an open
# cap 0.00-0.07
INWARD = 0.75
# ... and point by point (`orient_normals` on their lines) where more than MIXED faces away: the same
# clouds' true normals read 0.000-0.026, signed at random 0.48-0.53, plane fits exported unoriented
# (a plane fit's sign is arbitrary) 0.41-0.59
MIXED = 0.25
# A faceted skin's second reading (`fracture_likelihood`): taken where the first picks under
# EMPTY_PICK of the points; angles under FLAT_ANGLE (radians) are exactly flat, and a flat
# point's facet angle is its smallest larger one under FACET_DEG (a board's 90-degree edge is no
# facet). Plant pieces cut rough, smooth or flat, sampled with face normals (seeds 0-5): 0-18 of
# 2,500 points picked on 8 of 36 pieces; no piece of the bookshelves (seeds 0-5) or of the corpus's
# vessels (seeds 0-7) picks under 75.
EMPTY_PICK = 0.01
FLAT_ANGLE = 1e-4
FACET_DEG = 10.0


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
        away = inward_share(pts, normals)
        if away > INWARD:
            normals = -normals
            notes = tuple(notes) + (f"{label}: the given normals point into the solid; turned outward",)
        elif away > MIXED:
            normals = orient_normals(pts, normals)
            notes = tuple(notes) + (f"{label}: {away:.0%} of the given normals point into the solid, their signs "
                                    f"mixed; turned outward point by point",)
    return CloudFragment(name, pts, np.zeros((0, 3), np.int32), source, tuple(notes), normals)


def inward_share(points: np.ndarray, normals: np.ndarray) -> float:
    """The share of (N, 3) normals' weight that the views from around the cloud see facing away
    (`visibility_votes`): about 0 for outward normals, 1 for inward, a half for unoriented."""
    vote = visibility_votes(points, normals)
    total = float(np.abs(vote).sum())
    return -float(vote[vote < 0].sum()) / total if total > 0 else 0.0


def local_pca(points: np.ndarray, k: int = CLOUD_NEIGHBOURS,
              queries: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Principal axes of every point's k nearest points (itself included), or of the k nearest
    `points` of each of the (M, 3) `queries`.

    Returns
    -------
    values : (N, 3) eigenvalues of the neighbourhood covariance, ascending (M, 3 with queries)
    vectors : (N, 3, 3) the matching unit eigenvectors as columns (vectors[:, :, 0]: the normal)
    """
    from scipy.spatial import cKDTree

    queries = points if queries is None else queries
    k = min(k, len(points))
    _, idx = cKDTree(points).query(queries, k=k)
    q = points[idx.reshape(len(queries), k)]
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
                        spreads: float | None = None, majority: bool = False) -> np.ndarray:
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

    A faceted skin (a CAD model's, sampled with its face normals) puts many neighbours at exactly
    0 degrees and the rest at the facets' angle; averaged in the log, the zeros can drag the break
    under the split, so that nothing is picked. Where under EMPTY_PICK of the points are picked,
    the values are read again with each point whose roughness is exactly 0 given its smallest
    non-zero angle under FACET_DEG (the facets' own angle, not a constant floor).

    Parameters
    ----------
    points : (N, 3) array
    normals : (N, 3) unit normals (orientation is not used)
    k : neighbours per point
    spreads : the split's distance above the median in robust spreads (None: ROUGH_SPREADS)
    majority : split at Otsu's threshold where the median lies above it (most of the piece reads
        rough: an inner piece of a many-piece break), and give 0 everywhere where it does not

    Returns
    -------
    (N,) array in [0, 1]
    """
    angles, rough, idx, weight = _roughness(points, normals, k)
    likelihood = _rough_split(_smoothed_log(rough, idx, weight), spreads, majority)
    if majority or np.count_nonzero(likelihood >= 0.5) >= EMPTY_PICK * len(points):
        return likelihood
    facet = np.where(angles > FLAT_ANGLE, angles, np.inf).min(axis=1)
    faceted = (rough <= FLAT_ANGLE) & (facet < np.radians(FACET_DEG))
    if not faceted.any():
        return likelihood
    return _rough_split(_smoothed_log(np.where(faceted, facet, rough), idx, weight), spreads, majority)


def bulk_reads_rough(points: np.ndarray, normals: np.ndarray, k: int = CLOUD_NORMAL_NEIGHBOURS) -> bool:
    """Whether most of a cloud reads as rough as its break: the bulk's spread above its median
    roughness (`fracture_likelihood`'s split) lies above Otsu's split of the (N, 3) points' smoothed
    log roughness, so that the split is set by the skin's own roughness (a plant's faceted leaves
    and stem) and not between skin and break."""
    x = _smoothed_log(*_roughness(points, normals, k)[1:])
    centre = np.median(x)
    return bool(centre + ROUGH_SPREADS * 1.4826 * np.median(np.abs(x - centre)) > otsu_split(x, np.ones(len(x))))


def _roughness(points: np.ndarray, normals: np.ndarray, k: int):
    """Each point's angles (N, k - 1) to its k nearest points' normals (unsigned), its roughness
    (N,) (their ROUGH_QUANTILE), the neighbours (N, k) and their bilateral weights (N, k)."""
    from scipy.spatial import cKDTree

    k = min(k, len(points))
    _, idx = cKDTree(points).query(points, k=k)
    idx = idx.reshape(len(points), k)
    parallel = np.abs(np.einsum("nkd,nd->nk", normals[idx], normals))
    angles = np.arccos(np.clip(parallel[:, 1:], 0.0, 1.0)) if k > 1 else np.zeros((len(points), 1))
    return angles, np.quantile(angles, ROUGH_QUANTILE, axis=1), idx, parallel ** ROUGH_PARALLEL_POWER


def _smoothed_log(rough: np.ndarray, idx: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """(N,) log roughness averaged twice over each point's neighbours `idx` (N, k) with `weight` (N, k)."""
    x = np.log(np.maximum(rough, 1e-6))
    for _ in range(2):
        x = (weight * x[idx]).sum(axis=1) / weight.sum(axis=1)
    return x


def _rough_split(x: np.ndarray, spreads: float | None, majority: bool) -> np.ndarray:
    """(N,) likelihood of fracture from the smoothed log roughness x (N,): `fracture_likelihood`'s split."""
    # the smooth surface is most of a piece: the split lies above the bulk's own spread
    centre = np.median(x)
    noise = 1.4826 * np.median(np.abs(x - centre)) or 1.0
    spreads = ROUGH_SPREADS if spreads is None else spreads
    otsu = otsu_split(x, np.ones(len(x)))
    if majority:
        if centre <= otsu:
            return np.zeros(len(x))
        split = otsu
    else:
        split = max(otsu, centre + spreads * noise)
    from scipy.special import expit  # the logistic, without exp's overflow far below the split

    return expit((x - split) / noise)


# --- thinning -------------------------------------------------------------

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


def _median_spacing(q: np.ndarray) -> float:
    from scipy.spatial import cKDTree
    d, _ = cKDTree(q).query(q, k=2, workers=-1)
    nn = d[:, 1]
    nn = nn[nn > 0]
    return float(np.median(nn)) if len(nn) else 0.0
