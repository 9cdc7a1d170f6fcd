"""Synthetic fractures with a known answer.

`generate(shape, pieces, seed, ...)` builds a closed solid (a vase, a torso, a
slab, or any watertight mesh file), normalised to unit size (bounding-box
diagonal 1, centred on the origin), and breaks it into `pieces` single-body
fragments along rough fractal cut surfaces with manifold3d booleans.

Every piece is meshed on its own, as a scan would be: the two sides of each cut
are triangulated by two different grids (random rotation and offset) of the
same rough surface, so neighbours sample their common fracture at different
points and share no vertex positions (a last check slides any vertex that still
coincides with a neighbour's along an edge). The whole object is sampled at one
density, chosen so that the pieces have `faces` faces on average; the slivers
the booleans leave where a cut clips a triangle are collapsed or flipped away.
Scanner noise is added along the vertex normals and the pieces are scattered
to random poses.

The truth kept with each fragment: the 4x4 pose that carries its file
coordinates back into the object frame, which pieces touch (and over what
area), and which faces lie on fracture (cut) surfaces. `write` puts it on disk:

    OUT/fragments/<prefix>frag_00.ply ...
    OUT/truth.json     {"version": 1, "objects": [...], "fragments": [...],
                        "touching_pairs": [[name, name], ...], "contacts": [...]}
    OUT/labels.npz     one bool array per fragment name: True on fracture faces

Several objects can share one OUT (for grouping and assembly tests):
`write_many(results, out)` or repeated `write(result, out, prefix=...)`; every
fragment then names its "object" id in truth.json.

Everything is deterministic under `seed`; independent random streams drive the
shape, the cuts, the remeshing, the noise and the scatter, so that changing
the noise level does not change where the object breaks.
"""
from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .io.files import atomic_write_bytes, atomic_write_json, write_mesh
from .io.fragment import Fragment, FragmentError

SHAPES = ("vase", "torso", "slab")
TRUTH_VERSION = 1

# Fracture surface: fBm of Perlin noise, RMS height `roughness` (object units).
FBM_MAX_OCTAVES = 6
FBM_WAVELENGTH = 0.2  # of the coarsest octave, in object units (object diagonal = 1)
# Pieces below this fraction of the mean piece volume make the cut be drawn again.
MIN_VOLUME_FRACTION = 0.10
MAX_CUT_ATTEMPTS = 60
# Two pieces touch when more than CONTACT_FRACTION of the surface of one lies
# within CONTACT_DISTANCE of the other (measured on the exact, noise-free pieces).
CONTACT_DISTANCE = 0.005
CONTACT_FRACTION = 0.01
SCATTER_RANGE = 2.0  # translations uniform in [-2, 2]^3 object units
# Per built-in shape, measured over seeds 0-2 and 2/5/10 pieces, to choose the sampling
# density before building: surface area after normalising; fracture area (both sides)
# of K pieces / (K - 1)^0.75; and triangles x spacing^2 / area on the original and on
# the fracture surfaces after the sliver clean-up (2 on a plain grid).
_AREA_GUESS = {"vase": (1.55, 0.12, 2.25, 3.1), "torso": (0.84, 0.27, 2.2, 2.25), "slab": (1.11, 0.13, 2.1, 2.75)}
_AREA_GUESS_FILE = (None, 0.2, 2.2, 2.75)


@dataclass(eq=False)
class SynthResult:
    """A broken object with its known answer (see the module docstring)."""
    fragments: list[Fragment]
    poses: list[np.ndarray]  # pose i: 4x4 carrying fragment i's file coordinates into the object frame
    touching: list[tuple[int, int]]  # pairs (i, j), i < j, in sorted order
    shape: str
    seed: int
    params: dict
    fracture_faces: list[np.ndarray] = field(default_factory=list)  # (F_i,) bool per fragment
    contact_areas: list[float] = field(default_factory=list)  # parallel to `touching`, object units^2
    object_volume: float = 0.0
    piece_volumes: list[float] = field(default_factory=list)  # exact (pre-remesh) volumes
    timings: dict = field(default_factory=dict)

    def placed_back(self) -> list[Fragment]:
        """The fragments moved into the object frame by their truth poses."""
        return [f.transformed(p) for f, p in zip(self.fragments, self.poses)]


# --- the API ---------------------------------------------------------------

def generate(shape: str = "vase", pieces: int = 2, seed: int = 0, faces: int = 4000, noise: float = 0.0,
             roughness: float = 0.02, scatter: bool = True, progress: bool | None = None) -> SynthResult:
    """Break `shape` into `pieces` fragments of about `faces` faces each on average.

    shape: "vase", "torso", "slab", or the path of a closed (watertight) mesh file.
    noise: standard deviation of the scanner noise along the normals (object diagonal = 1).
    roughness: RMS height of the cut surfaces about their mean plane (object diagonal = 1).
    progress: a tqdm bar on stderr; None shows it when stderr is a terminal.
    """
    import manifold3d as mf

    pieces, faces, seed = int(pieces), int(faces), int(seed)
    if pieces < 1:
        raise ValueError(f"pieces must be at least 1, got {pieces}")
    if faces < 200:
        raise ValueError(f"faces must be at least 200 per piece, got {faces}")
    if not (0.0 <= noise <= 0.02):
        raise ValueError(f"noise must lie in [0, 0.02] (a fraction of the object size), got {noise}")
    if not (0.0 <= roughness <= 0.1):
        raise ValueError(f"roughness must lie in [0, 0.1] (a fraction of the object size), got {roughness}")
    if seed < 0:
        raise ValueError(f"seed must be non-negative, got {seed}")
    shape_rng, cut_rng, mesh_rng, noise_rng, scatter_rng = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(5))
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    # One sampling density for the whole object, as a scanner has: triangles of about
    # spacing^2 / 2, chosen so that the pieces have `faces` faces on average.
    area, frac_area, c_orig, c_frac = _AREA_GUESS.get(shape, _AREA_GUESS_FILE)
    if area is None:  # a file: its area is known once loaded
        obj = make_shape(shape, seed, detail=None, _rng=shape_rng)
        area = obj.surface_area()
    spacing = math.sqrt((c_orig * area + c_frac * frac_area * (pieces - 1) ** 0.75) / (pieces * faces))
    if shape in SHAPES:
        obj = make_shape(shape, seed, detail=spacing, _rng=shape_rng)
    else:
        obj = obj.refine_to_length(spacing * 1.3).as_original()
    shape_name = shape if shape in SHAPES else str(shape)
    object_volume = obj.volume()
    timings["shape"] = time.perf_counter() - t0

    show = sys.stderr.isatty() if progress is None else bool(progress)
    timings["fracture"] = timings["mesh"] = 0.0
    # A cut that leaves a piece the clean-up cannot make a clean closed mesh is a rare
    # accident of the booleans: the object is broken again from another random stream.
    for attempt in range(3):
        bar = _progress_bar(pieces - 1, show, f"synth {Path(shape_name).name}")
        try:
            t0 = time.perf_counter()
            parts, object_id, octaves = _fracture(obj, pieces, roughness, spacing, cut_rng, bar)
            timings["fracture"] += time.perf_counter() - t0
        finally:
            bar.close()
        t0 = time.perf_counter()
        meshes = [_clean_slivers(*_manifold_arrays(part, object_id), spacing) for part in parts]
        faults = [(k, _closed_mesh_fault(v, f, 2 - 2 * part.genus(), part.volume()))
                  for k, ((v, f, _), part) in enumerate(zip(meshes, parts))]
        faults = [(k, why) for k, why in faults if why is not None]
        timings["mesh"] += time.perf_counter() - t0
        if not faults:
            break
        cut_rng = np.random.default_rng(np.random.SeedSequence([seed, 7919, attempt]))
    else:  # a bug, not a user fault
        raise RuntimeError(f"synth: piece {faults[0][0]} of {shape_name} (seed {seed}) is not a clean closed mesh "
                           f"after 3 fractures: {faults[0][1]}")
    timings["retries"] = attempt

    t0 = time.perf_counter()
    touching, contact_areas = _touching_pairs([m[0] for m in meshes], [m[1] for m in meshes])
    timings["touching"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    vertices = _separate_shared_vertices([m[0] for m in meshes], [m[1] for m in meshes], mesh_rng)
    if noise > 0:
        vertices = [v + _vertex_normals(v, m[1]) * noise_rng.normal(0.0, noise, (len(v), 1))
                    for v, m in zip(vertices, meshes)]
    width = max(2, len(str(pieces - 1)))
    fragments, poses = [], []
    for i, (v, m) in enumerate(zip(vertices, meshes)):
        placement = _random_placement(v, scatter_rng) if scatter else np.eye(4)
        v_file = v @ placement[:3, :3].T + placement[:3, 3]
        fragments.append(Fragment(f"frag_{i:0{width}d}", v_file, m[1].astype(np.int32), None, ()))
        poses.append(_invert_rigid(placement))
    timings["finish"] = time.perf_counter() - t0

    params = {"shape": shape_name, "pieces": pieces, "seed": seed, "faces": faces, "noise": float(noise),
              "roughness": float(roughness), "scatter": bool(scatter), "spacing": spacing,
              "fbm_octaves": octaves, "fbm_wavelength": FBM_WAVELENGTH,
              "contact_distance": CONTACT_DISTANCE, "contact_fraction": CONTACT_FRACTION}
    return SynthResult(fragments, poses, touching, shape_name, seed, params,
                       fracture_faces=[m[2] for m in meshes], contact_areas=contact_areas,
                       object_volume=float(object_volume), piece_volumes=[float(p.volume()) for p in parts],
                       timings=timings)


def make_shape(shape: str = "vase", seed: int = 0, detail: float | None = 0.015,
               _rng: np.random.Generator | None = None):
    """The unbroken object as a manifold3d.Manifold, normalised (bbox diagonal 1, centred).

    Built-in shapes vary a little with `seed` (proportions within about 10%), so
    that objects of different seeds are different objects; they are tessellated
    into triangles of about detail^2 / 2 (object units). A file is used as is
    (refined to `detail` when one is given).
    """
    rng = _rng if _rng is not None else np.random.default_rng(np.random.SeedSequence(int(seed)).spawn(5)[0])
    if shape == "vase":
        solid = _vase(rng, detail * 1.96)  # the factors: measured, for triangles of detail^2 / 2
    elif shape == "torso":
        solid = _torso(rng, detail * 2.0)
    elif shape == "slab":
        solid = _slab(rng, detail * 1.33)
    else:
        solid = _normalise(_solid_from_file(shape))
        return (solid.refine_to_length(detail * 1.3) if detail else solid).as_original()
    return _normalise(solid).as_original()


def write(result: SynthResult, out_dir, prefix: str = "") -> dict:
    """Write the fragments, labels and truth of one object into out_dir (see the module docstring).

    An out_dir that already holds a truth.json gets this object added to it; an
    object written before with the same prefix is replaced. Returns the truth dict.
    """
    return write_many([result], out_dir, prefixes=[prefix])


def write_many(results: list[SynthResult], out_dir, prefixes: list[str] | None = None) -> dict:
    """Write several objects into one out_dir, fragment names prefixed per object.

    Default prefixes are "o0_", "o1_", ... (or "" for a single object).
    """
    results = list(results)
    if prefixes is None:
        prefixes = [""] if len(results) == 1 else [f"o{k}_" for k in range(len(results))]
    prefixes = list(prefixes)
    if len(prefixes) != len(results):
        raise ValueError(f"{len(results)} results but {len(prefixes)} prefixes")
    if len(set(prefixes)) != len(prefixes):
        raise ValueError(f"prefixes must differ, got {prefixes}")
    for p in prefixes:
        if not all(c.isalnum() or c in "_-." for c in p):
            raise ValueError(f"prefix {p!r} may hold only letters, digits, '_', '-' and '.'")

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise FragmentError(f"{out}: exists and is not a directory")
    frag_dir = out / "fragments"
    truth_path = out / "truth.json"
    labels_path = out / "labels.npz"
    truth = read_truth(out) if truth_path.exists() else {
        "version": TRUTH_VERSION, "objects": [], "fragments": [], "touching_pairs": [], "contacts": []}
    labels = load_labels(out) if labels_path.exists() else {}

    # Drop the objects being rewritten (same prefix); remember their files.
    replaced = {o["id"] for o in truth["objects"] if o.get("prefix", "") in prefixes}
    stale_files = [e["file"] for e in truth["fragments"] if e["object"] in replaced]
    stale_names = {e["name"] for e in truth["fragments"] if e["object"] in replaced}
    truth["objects"] = [o for o in truth["objects"] if o["id"] not in replaced]
    truth["fragments"] = [e for e in truth["fragments"] if e["object"] not in replaced]
    truth["touching_pairs"] = [p for p in truth["touching_pairs"] if p[0] not in stale_names]
    truth["contacts"] = [c for c in truth["contacts"] if c["a"] not in stale_names]
    for n in stale_names:
        labels.pop(n, None)

    kept_names = {e["name"] for e in truth["fragments"]}
    kept_files = {e["file"] for e in truth["fragments"]}
    next_id = max([o["id"] for o in truth["objects"]], default=-1) + 1
    plans = []
    for k, (result, prefix) in enumerate(zip(results, prefixes)):
        names = [prefix + f.name for f in result.fragments]
        for n in names:
            rel = f"fragments/{n}.ply"
            if n in kept_names or rel in kept_files:
                raise FragmentError(f"{out / rel}: already belongs to another object of {truth_path}; "
                                    f"choose another prefix")
            if (out / rel).exists() and rel not in stale_files:
                raise FragmentError(f"{out / rel}: exists and is not listed in {truth_path}; refusing to overwrite it")
        plans.append((next_id + k, result, prefix, names))

    new_files = set()
    for object_id, result, prefix, names in plans:
        for frag, name in zip(result.fragments, names):
            write_mesh(frag_dir / f"{name}.ply", frag.vertices, frag.faces)
            new_files.add(f"fragments/{name}.ply")
        for name, lab in zip(names, result.fracture_faces):
            labels[name] = np.asarray(lab, bool)
        truth["objects"].append({
            "id": object_id, "prefix": prefix, "shape": result.shape, "seed": result.seed,
            "params": result.params, "volume": result.object_volume, "fragments": names})
        for i, (frag, name, pose) in enumerate(zip(result.fragments, names, result.poses)):
            truth["fragments"].append({
                "file": f"fragments/{name}.ply", "name": name, "object": object_id,
                "pose": np.asarray(pose, float).tolist(),
                "vertices": int(len(frag.vertices)), "faces": int(len(frag.faces)),
                "fracture_faces": int(np.count_nonzero(result.fracture_faces[i])) if result.fracture_faces else None,
                "volume": result.piece_volumes[i] if result.piece_volumes else None})
        for (i, j), area in zip(result.touching, result.contact_areas or [None] * len(result.touching)):
            truth["touching_pairs"].append([names[i], names[j]])
            truth["contacts"].append({"a": names[i], "b": names[j], "area": area})

    import io as _io
    buf = _io.BytesIO()
    np.savez_compressed(buf, **labels)
    atomic_write_bytes(labels_path, buf.getvalue())
    atomic_write_json(truth_path, truth)  # last: truth.json indexes what is on disk
    for rel in stale_files:
        if rel not in new_files:
            (out / rel).unlink(missing_ok=True)
    return truth


def read_truth(path) -> dict:
    """Read OUT/truth.json (give OUT or the file); poses come back as 4x4 float arrays."""
    p = Path(path)
    if p.is_dir():
        p = p / "truth.json"
    try:
        truth = json.loads(p.read_text())
    except FileNotFoundError:
        raise FragmentError(f"{p}: no such file") from None
    except (OSError, ValueError) as exc:
        raise FragmentError(f"{p}: unreadable truth file ({exc})") from None
    if not isinstance(truth, dict) or truth.get("version") != TRUTH_VERSION or "fragments" not in truth:
        raise FragmentError(f"{p}: not a relicgpu truth file of version {TRUTH_VERSION}")
    for entry in truth["fragments"]:
        entry["pose"] = np.asarray(entry["pose"], np.float64)
    return truth


def load_labels(path) -> dict[str, np.ndarray]:
    """OUT/labels.npz as {fragment name: (F,) bool, True on fracture faces}."""
    p = Path(path)
    if p.is_dir():
        p = p / "labels.npz"
    try:
        with np.load(p) as data:
            return {k: data[k].astype(bool) for k in data.files}
    except FileNotFoundError:
        raise FragmentError(f"{p}: no such file") from None
    except (OSError, ValueError) as exc:
        raise FragmentError(f"{p}: unreadable labels file ({exc})") from None


# --- shapes ----------------------------------------------------------------

def _jitter(rng, value, rel=0.08):
    return value * (1.0 + rng.uniform(-rel, rel))


def _vase(rng, edge):
    """A pot: a smooth profile revolved, walls and bottom about 5% of the height thick."""
    import manifold3d as mf

    foot, belly, neck, lip = _jitter(rng, 0.16), _jitter(rng, 0.33), _jitter(rng, 0.13), _jitter(rng, 0.18)
    s_belly = _jitter(rng, 0.42, 0.15)
    ctrl_s = [0.0, 0.06, s_belly, 0.80, 0.90, 1.0]
    ctrl_r = [foot, foot * 1.15, belly, neck, neck * 1.06, lip]
    height, wall = 1.0, 0.05
    z = np.linspace(0.0, height, int(np.clip(1.6 / edge, 32, 400)))
    r_out, slope = _pchip(np.array(ctrl_s), np.array(ctrl_r), z / height)
    slope = slope / height
    r_in = r_out - wall * np.sqrt(1.0 + slope ** 2)  # horizontal offset giving a normal thickness `wall`
    inner = z >= wall
    polygon = np.vstack([[0.0, 0.0], np.c_[r_out, z], np.c_[r_in[inner], z[inner]][::-1], [0.0, wall]])
    segments = 4 * int(np.clip(2 * np.pi * belly / edge / 4, 12, 128))
    return mf.Manifold.revolve(mf.CrossSection([polygon]), segments)


def _torso(rng, edge):
    """A rounded body: chest, belly, hips, shoulders and neck blended by a smooth union.

    The blended signed distance is star-shaped about a point of the chest, so the
    surface is found along rays from it and a geodesic sphere is moved onto it:
    always one closed, non-self-intersecting manifold.
    """
    import manifold3d as mf

    j = lambda v: _jitter(rng, v)
    ellipsoids = [
        ((0.0, 0.0, 0.30), (j(0.40), j(0.24), j(0.30))),   # chest
        ((0.0, 0.10, 0.30), (j(0.30), j(0.15), j(0.20))),  # chest plate
        ((0.0, 0.02, -0.02), (j(0.32), j(0.22), j(0.28))),  # belly
        ((0.0, -0.01, -0.32), (j(0.36), j(0.24), j(0.20))),  # hips
    ]
    shoulder = j(0.38)
    capsules = [
        ((-shoulder, 0.0, 0.45), (shoulder, 0.0, 0.45), j(0.13)),  # shoulders
        ((0.0, 0.0, 0.50), (0.0, 0.0, j(0.72)), j(0.09)),  # neck
    ]
    blend = 0.08
    centre = np.array([0.0, 0.0, -0.08])

    def sdf(p):
        d = None
        for c, r in ellipsoids:
            q = (p - c) / np.asarray(r)
            k0 = np.sqrt((q * q).sum(axis=-1))
            q = q / np.asarray(r)
            k1 = np.sqrt((q * q).sum(axis=-1))
            e = k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)  # a bound of the ellipsoid's distance (Quilez)
            d = e if d is None else _smooth_min(d, e, blend)
        for a, b, r in capsules:
            a, b = np.asarray(a), np.asarray(b)
            ab = b - a
            t = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
            x = p - (a + t[..., None] * ab)
            e = np.sqrt((x * x).sum(axis=-1)) - r
            d = _smooth_min(d, e, blend)
        return d

    sphere = mf.Manifold.sphere(1.0, 4 * int(np.clip(2 * np.pi * 0.6 / edge / 4, 24, 150)))
    mesh = sphere.to_mesh64()
    dirs = np.asarray(mesh.vert_properties)[:, :3]
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    radius = _outermost_root(sdf, dirs, centre, t_max=1.2)
    verts = centre + radius[:, None] * dirs
    return mf.Manifold(mf.Mesh64(np.ascontiguousarray(verts), np.array(mesh.tri_verts, np.uint64, order="C")))


def _pchip(x, y, t):
    """Monotone cubic (Fritsch-Carlson) interpolation of (x, y) at t: values and derivatives."""
    h = np.diff(x)
    delta = np.diff(y) / h
    d = np.zeros_like(y)
    for k in range(1, len(x) - 1):
        if delta[k - 1] * delta[k] > 0:
            w1, w2 = 2 * h[k] + h[k - 1], h[k] + 2 * h[k - 1]
            d[k] = (w1 + w2) / (w1 / delta[k - 1] + w2 / delta[k])
    d[0], d[-1] = delta[0], delta[-1]
    k = np.clip(np.searchsorted(x, t, side="right") - 1, 0, len(x) - 2)
    s = (t - x[k]) / h[k]
    h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
    value = h00 * y[k] + h10 * h[k] * d[k] + h01 * y[k + 1] + h11 * h[k] * d[k + 1]
    dh00, dh10, dh01, dh11 = 6 * s**2 - 6 * s, 3 * s**2 - 4 * s + 1, -6 * s**2 + 6 * s, 3 * s**2 - 2 * s
    deriv = (dh00 * y[k] + dh01 * y[k + 1]) / h[k] + dh10 * d[k] + dh11 * d[k + 1]
    return value, deriv


def _smooth_min(a, b, k):
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * k * 0.25


def _outermost_root(f, dirs, centre, t_max, steps=32, iters=22):
    """Per ray centre + t * dir, the largest t in (0, t_max) where f goes from inside (<0) to outside."""
    ts = np.linspace(t_max, 0.0, steps)
    values = f(centre + ts[None, :, None] * dirs[:, None, :])  # (rays, steps)
    inside = values < 0
    if not inside.any(axis=1).all():
        raise RuntimeError("torso: a ray from the centre misses the body")
    k = inside.argmax(axis=1)  # first sample inside, coming from outside
    lo, hi = ts[k], ts[np.maximum(k - 1, 0)]
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        inside = f(centre + mid[:, None] * dirs) < 0
        lo = np.where(inside, mid, lo)
        hi = np.where(inside, hi, mid)
    return 0.5 * (lo + hi)


def _slab(rng, edge):
    """A thick tile (about 1 x 0.66 x 0.08), bent slightly like a roof tile."""
    import manifold3d as mf

    size = (1.0, _jitter(rng, 0.66), _jitter(rng, 0.08))
    bend_x, bend_y, twist = _jitter(rng, 0.28), _jitter(rng, 0.06), rng.uniform(-0.04, 0.04)
    box = mf.Manifold.cube(size, True).refine_to_length(edge)

    def bend(p):
        p = np.array(p, np.float64, copy=True)
        x, y = p[:, 0], p[:, 1]
        p[:, 2] += bend_x * x * x + bend_y * y * y + twist * x * y
        return p

    return box.warp_batch(bend)


def _solid_from_file(path) -> "object":
    import manifold3d as mf
    from .io.fragment import is_watertight
    from .io.load import load_fragment

    p = Path(path)
    if not p.exists():
        raise FragmentError(f"{p}: no such file; --shape takes vase, torso, slab or the path of a closed mesh")
    frag = load_fragment(p)
    # Merge coincident vertices (STL stores every triangle apart) before checking closure.
    v, inverse = np.unique(frag.vertices, axis=0, return_inverse=True)
    f = inverse.reshape(-1)[frag.faces.astype(np.int64)]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    if len(f) == 0 or not is_watertight(f):
        open_edges = _count_bad_edges(f)
        raise FragmentError(f"{p}: the mesh is not watertight ({open_edges} open or non-manifold edges); "
                            f"synth needs a closed solid")
    solid = mf.Manifold(mf.Mesh64(np.ascontiguousarray(v, np.float64), np.ascontiguousarray(f, np.uint64)))
    if solid.status() != mf.Error.NoError or solid.is_empty():
        raise FragmentError(f"{p}: manifold3d rejects the mesh ({solid.status().name}); synth needs a closed, "
                            f"consistently oriented solid")
    if solid.volume() < 0:
        solid = mf.Manifold(mf.Mesh64(np.ascontiguousarray(v, np.float64), np.ascontiguousarray(f[:, ::-1], np.uint64)))
    if solid.volume() <= 0:
        raise FragmentError(f"{p}: the closed mesh encloses no volume")
    return solid


def _count_bad_edges(faces) -> int:
    if len(faces) == 0:
        return 0
    f = np.asarray(faces, np.int64)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return int(np.count_nonzero(counts != 2))


def _normalise(solid):
    x0, y0, z0, x1, y1, z1 = solid.bounding_box()
    lo, hi = np.array([x0, y0, z0]), np.array([x1, y1, z1])
    scale = 1.0 / float(np.linalg.norm(hi - lo))
    centre = 0.5 * (lo + hi)
    m = np.zeros((3, 4))
    m[:, :3] = np.eye(3) * scale
    m[:, 3] = -centre * scale
    return solid.transform(m)


# --- fracture --------------------------------------------------------------

def _fracture(obj, pieces, roughness, spacing, rng, bar):
    """Split the largest piece along a rough surface until there are `pieces` single bodies.

    Each cut is one rough surface (a random plane through the piece, displaced by
    fBm noise), but its two sides are triangulated apart: the piece is intersected
    with one cutter and differenced with another, two grids of the same surface at
    random rotations and offsets. So neighbours sample their common fracture at
    different points, as two scans would, and match up to the linear
    interpolation error of the grids, which grows with the finest octaves kept
    (measured over the three shapes, 2 pieces, with FBM_* as set here: RMS gap
    1e-3 to 1.8e-3 of the object size, at most 7e-3, at 4000 and at 20000 faces).
    Returns the pieces, the original id of the object's faces and the octave count.
    """
    object_id = obj.original_id()
    parts, volumes = [obj], [obj.volume()]
    min_volume = MIN_VOLUME_FRACTION * volumes[0] / pieces
    octaves = _octaves(spacing)
    for _ in range(pieces - 1):
        k = int(np.argmax(volumes))
        piece = parts[k]
        v, f, _ = _manifold_arrays(piece, object_id)
        centres = v[f].mean(axis=1)
        areas = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
        # Cut across the piece's longest extent (with a random tilt), so that pieces stay
        # compact like real sherds rather than long strips.
        mean = (centres * areas[:, None]).sum(0) / areas.sum()
        cov = ((centres - mean) * areas[:, None]).T @ (centres - mean)
        long_axis = np.linalg.eigh(cov)[1][:, -1]
        # LAPACK's sign of an eigenvector differs between CPUs (it broke the same seed into other
        # pieces on Intel and AMD hosts): fix it, so that a seed is one object everywhere
        long_axis = long_axis * np.sign(long_axis[np.argmax(np.abs(long_axis))])
        for attempt in range(MAX_CUT_ATTEMPTS):
            tilt = 0.6 if attempt < MAX_CUT_ATTEMPTS // 2 else 3.0  # then nearly any plane
            normal = long_axis + tilt * _random_unit(rng)
            normal /= np.linalg.norm(normal)
            origin = normal * _weighted_quantile(centres @ normal, areas, rng.uniform(0.3, 0.7))
            reach = float(np.linalg.norm(v - origin, axis=1).max()) + 3 * spacing
            height = _fbm(reach, octaves, roughness, rng)
            below = piece ^ _cutter(v, normal, origin, height, reach, spacing, rng)
            above = piece - _cutter(v, normal, origin, height, reach, spacing, rng)
            if below.is_empty() or above.is_empty():
                continue
            if below.volume() < min_volume or above.volume() < min_volume:
                continue
            if len(below.decompose()) != 1 or len(above.decompose()) != 1:
                continue
            break
        else:
            raise ValueError(f"could not cut a piece into two single bodies of at least {MIN_VOLUME_FRACTION:.0%} "
                             f"of the mean piece volume in {MAX_CUT_ATTEMPTS} tries; ask for fewer pieces")
        parts[k] = below
        volumes[k] = below.volume()
        parts.append(above)
        volumes.append(above.volume())
        bar.update(1)
    return parts, object_id, octaves


def _octaves(spacing):
    """fBm octaves whose wavelength spans at least 2.5 grid steps (finer ones a scan at
    this density could not show). Real fracture surfaces are rough down to the scan's
    resolution; with a high gain the finest octaves make them rougher than scanner noise
    at the scale of the triangles, which is what tells fracture from original surface."""
    n = 1
    while n < FBM_MAX_OCTAVES and FBM_WAVELENGTH / 2 ** n >= 2.5 * spacing:
        n += 1
    return n


def _cutter(points, normal, origin, height, reach, spacing, rng):
    """A closed box whose top face is the rough surface `height` over the plane through
    `origin` facing `normal`, triangulated on a grid of step `spacing` at a random
    rotation and offset. It covers `points` (the piece to cut) sideways and below,
    so piece ^ cutter and piece - cutter are the two sides of the surface."""
    import manifold3d as mf

    u0, w0 = _frame(normal)
    angle = rng.uniform(0.0, 2.0 * np.pi)
    u = math.cos(angle) * u0 + math.sin(angle) * w0
    w = np.cross(normal, u)
    rel = points - origin
    a, b, c = rel @ u, rel @ w, rel @ normal
    margin = 2 * spacing
    shift = rng.uniform(0.0, spacing, 2)
    ga, gb = np.meshgrid(a.min() - margin - shift[0] + spacing * np.arange(int((np.ptp(a) + 2 * margin) / spacing) + 3),
                         b.min() - margin - shift[1] + spacing * np.arange(int((np.ptp(b) + 2 * margin) / spacing) + 3),
                         indexing="ij")
    # The surface is a function of the unrotated plane coordinates, shared by both cutters of a cut.
    x = ga * math.cos(angle) - gb * math.sin(angle)
    y = ga * math.sin(angle) + gb * math.cos(angle)
    h = height(x, y)
    depth = max(-c.min(), -h.min(), 0.0) + margin  # the bottom lies under the piece and the surface
    local, tris = _heightfield_box(ga, gb, h, -depth)
    world = origin + local @ np.stack([u, w, normal])
    return mf.Manifold(mf.Mesh64(np.ascontiguousarray(world), np.ascontiguousarray(tris, np.uint64)))


def _heightfield_box(ga, gb, height, bottom):
    """Vertices (local a, b, c) and outward triangles of the solid under a height field."""
    na, nb = ga.shape[0] - 1, ga.shape[1] - 1
    idx = np.arange((na + 1) * (nb + 1)).reshape(na + 1, nb + 1)
    top = np.c_[ga.ravel(), gb.ravel(), height.ravel()]
    p00, p10, p01, p11 = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel()
    top_tris = np.concatenate([np.c_[p00, p10, p11], np.c_[p00, p11, p01]])
    # The top's boundary, counter-clockwise seen from +c, without repeated corners.
    ring = np.concatenate([idx[:, 0], idx[-1, 1:], idx[-2::-1, -1], idx[0, -2:0:-1]])
    n_top, n_ring = len(top), len(ring)
    bottom_ring = np.c_[top[ring, 0], top[ring, 1], np.full(n_ring, bottom)]
    centre = np.array([[ga.mean(), gb.mean(), bottom]])
    verts = np.vstack([top, bottom_ring, centre])
    t = ring
    bk = n_top + np.arange(n_ring)
    t1, b1 = np.roll(t, -1), np.roll(bk, -1)
    c = np.full(n_ring, n_top + n_ring)
    side = np.concatenate([np.c_[t, bk, b1], np.c_[t, b1, t1]])
    cap = np.c_[c, b1, bk]
    return verts, np.concatenate([top_tris, side, cap])


def _fbm(reach, octaves, roughness, rng, gain=0.8):
    """A random fractal height function h(x, y) over [-reach, reach]^2: Perlin noise
    octaves of halving wavelength, scaled to an RMS height of `roughness`."""
    layers, norm = [], 0.0
    for octave in range(octaves):
        wavelength = FBM_WAVELENGTH / 2 ** octave
        n = int(2 * reach / wavelength) + 3
        angles = rng.uniform(0, 2 * np.pi, (n, n))
        layers.append((wavelength, gain ** octave, np.stack([np.cos(angles), np.sin(angles)], axis=-1),
                       rng.uniform(0, 1, 2)))
        norm += gain ** (2 * octave)
    # 0.2157: the standard deviation of one octave of this Perlin noise (measured over 2e6 points).
    scale = roughness / (0.2157 * math.sqrt(norm))

    def height(x, y):
        total = np.zeros(np.shape(x))
        if roughness == 0:
            return total
        for wavelength, amp, grads, offset in layers:
            gx = np.clip((x + reach) / wavelength + offset[0], 0, grads.shape[0] - 1.001)
            gy = np.clip((y + reach) / wavelength + offset[1], 0, grads.shape[1] - 1.001)
            total += amp * _perlin(gx, gy, grads)
        return total * scale

    return height


def _perlin(x, y, grads):
    xi, yi = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    xf, yf = x - xi, y - yi

    def dot(ix, iy, dx, dy):
        g = grads[ix, iy]
        return g[..., 0] * dx + g[..., 1] * dy

    n00, n10 = dot(xi, yi, xf, yf), dot(xi + 1, yi, xf - 1, yf)
    n01, n11 = dot(xi, yi + 1, xf, yf - 1), dot(xi + 1, yi + 1, xf - 1, yf - 1)
    u = xf * xf * xf * (xf * (xf * 6 - 15) + 10)
    v = yf * yf * yf * (yf * (yf * 6 - 15) + 10)
    lower, upper = n00 + u * (n10 - n00), n01 + u * (n11 - n01)
    return lower + v * (upper - lower)


# --- remeshing -------------------------------------------------------------

def _manifold_arrays(solid, object_id):
    """Vertices, triangles and per-triangle fracture flags (not from the original object) of a Manifold."""
    mesh = solid.to_mesh64()
    v = np.array(mesh.vert_properties, np.float64)[:, :3]
    f = np.array(mesh.tri_verts, np.int64)
    run_index = np.asarray(mesh.run_index, np.int64)
    run_ids = np.asarray(mesh.run_original_id)
    fracture = np.repeat(run_ids != object_id, np.diff(run_index) // 3)  # run_index counts tri_verts entries
    return v, f, fracture


def _clean_slivers(v, f, labels, spacing, min_edge=0.2, flat_degrees=10.0, passes=3):
    """Remove the needle and cap triangles the booleans leave where a cut clips a triangle.

    Edges shorter than min_edge x spacing are collapsed (shortest first) when the
    link condition holds, so the mesh stays a closed manifold of the same topology;
    the surviving vertex keeps the position of the endpoint on a crease (a sharp
    edge or the border between fracture and original faces), so creases stay put,
    and a collapse that would turn a face over is skipped. Then the long edge of
    each remaining cap is flipped where its two faces are nearly coplanar (or the
    cap has no area). A few passes, until nothing changes. Returns (v, f, labels).
    """
    v = np.array(v, np.float64, copy=True)
    f = np.array(f, np.int64, copy=True)
    labels = np.asarray(labels, bool).copy()
    for _ in range(passes):
        f, labels, collapsed = _collapse_short_edges(v, f, labels, spacing, min_edge)
        f, labels, flipped = _flip_caps(v, f, labels, spacing, flat_degrees)
        if not collapsed:
            break
    v, f = _drop_unused(v, f)
    return v, f, labels


def _collapse_short_edges(v, f, labels, spacing, min_edge):
    """One pass of short-edge collapses (see _clean_slivers); moves v in place."""
    alive = np.ones(len(f), bool)
    fn = _unit_normals(v, f)
    area2 = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    speck = 1e-6 * spacing * spacing  # faces below this have no trustworthy normal
    sharp_cos = math.cos(math.radians(30.0))
    # A vertex is on a crease if an incident edge is sharp or its faces carry both labels.
    e_lo, e_hi, e_f0, e_f1 = _edge_faces(f)
    sharp = np.einsum("ij,ij->i", fn[e_f0], fn[e_f1]) < sharp_cos
    sharp &= (area2[e_f0] > speck) & (area2[e_f1] > speck)
    border = labels[e_f0] != labels[e_f1]
    crease = np.zeros(len(v), bool)
    crease[e_lo[sharp | border]] = True
    crease[e_hi[sharp | border]] = True
    length = np.linalg.norm(v[e_lo] - v[e_hi], axis=1)
    short = np.flatnonzero(length < min_edge * spacing)
    if len(short) == 0:
        return f, labels, 0

    vert_faces = [set() for _ in range(len(v))]
    for k, tri in enumerate(f.tolist()):
        for x in tri:
            vert_faces[x].add(k)
    collapsed = 0
    for e in short[np.argsort(length[short])]:
        a, b = int(e_lo[e]), int(e_hi[e])
        shared = vert_faces[a] & vert_faces[b]
        if len(shared) != 2:  # the edge is gone already
            continue
        opposite = {int(x) for k in shared for x in f[k]} - {a, b}
        ring_a = {int(x) for k in vert_faces[a] for x in f[k]} - {a}
        ring_b = {int(x) for k in vert_faces[b] for x in f[k]} - {b}
        if (ring_a & ring_b) != opposite:  # link condition: the collapse would pinch the surface
            continue
        if crease[b] and not crease[a]:
            a, b = b, a
        # b merges into a; try a's position, then b's and the midpoint (when a is no crease vertex).
        changed = sorted((vert_faces[a] | vert_faces[b]) - shared)
        tris = np.where(f[changed] == b, a, f[changed])
        candidates = [v[a].copy()] + ([v[b].copy(), 0.5 * (v[a] + v[b])] if not crease[a] or crease[b] else [])
        reliable = area2[changed] > speck
        for pos in candidates:
            p = v[tris]
            p[tris == a] = pos
            n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
            norm = np.linalg.norm(n, axis=1)
            turn = np.einsum("ij,ij->i", n, fn[changed]) > 0.5 * norm
            if (norm[reliable] > speck).all() and turn[reliable].all():
                break
        else:
            continue
        v[a] = pos
        f[changed] = tris
        fn[changed] = n / np.maximum(norm, 1e-300)[:, None]
        area2[changed] = norm
        for k in shared:
            alive[k] = False
            for x in f[k]:
                vert_faces[x].discard(k)
        vert_faces[a] = set(changed)
        vert_faces[b] = set()
        crease[a] = crease[a] or crease[b]
        collapsed += 1
    return f[alive], labels[alive], collapsed


def _flip_caps(v, f, labels, spacing, flat_degrees):
    """Flip the longest edge of triangles with an angle over 150 degrees where the two
    faces are nearly coplanar and carry the same label, and the flip raises the smaller
    angle. A cap without area is flipped whatever its neighbour: its apex lies on the
    edge, so the flip does not change the surface."""
    f, labels = f.copy(), labels.copy()
    fn = _unit_normals(v, f)
    area2 = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    speck = 1e-6 * spacing * spacing
    flat_cos = math.cos(math.radians(flat_degrees))
    angles = _corner_angles(v, f)
    caps = np.flatnonzero(angles.max(axis=1) > 150.0)
    if len(caps) == 0:
        return f, labels, 0
    e_lo, e_hi, e_f0, e_f1 = _edge_faces(f)
    nv = len(v)
    keys = e_lo * nv + e_hi  # sorted, as _edge_faces sorts by (lo, hi)
    new_edges: set[int] = set()

    def edge_of(x, y):
        key = min(x, y) * nv + max(x, y)
        i = int(np.searchsorted(keys, key))
        return i if i < len(keys) and keys[i] == key else None

    touched = set()
    for t in caps:
        if t in touched:
            continue
        corner = int(np.argmax(angles[t]))
        apex = int(f[t, corner])
        a, b = int(f[t, (corner + 1) % 3]), int(f[t, (corner + 2) % 3])
        k = edge_of(a, b)
        if k is None:
            continue
        other = int(e_f1[k] if e_f0[k] == t else e_f0[k])
        if other in touched:
            continue
        flat = area2[t] <= speck
        if not flat and (labels[other] != labels[t] or fn[t] @ fn[other] < flat_cos):
            continue
        far = int(next(x for x in f[other] if x != a and x != b))
        if edge_of(apex, far) is not None or min(apex, far) * nv + max(apex, far) in new_edges:
            continue
        # t = (apex, a, b) in its winding; the flip gives (apex, a, far) and (apex, far, b).
        new = np.array([[apex, a, far], [apex, far, b]])
        n = np.cross(v[new[:, 1]] - v[new[:, 0]], v[new[:, 2]] - v[new[:, 0]])
        reference = fn[other] if flat else fn[t]
        if (np.linalg.norm(n, axis=1) <= speck).any() or (n @ reference <= 0).any():
            continue
        if _corner_angles(v, new).min() <= min(angles[t].min(), _corner_angles(v, f[[other]]).min()):
            continue
        f[t], f[other] = new
        if flat:
            labels[t] = labels[other]
        new_edges.add(min(apex, far) * nv + max(apex, far))
        touched.update((t, other))
    return f, labels, len(touched) // 2


def _corner_angles(v, f):
    t = v[f]
    out = np.empty((len(f), 3))
    for k in range(3):
        u, w = t[:, (k + 1) % 3] - t[:, k], t[:, (k + 2) % 3] - t[:, k]
        c = np.einsum("ij,ij->i", u, w) / np.maximum(np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1), 1e-300)
        out[:, k] = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
    return out


def _unit_normals(v, f):
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def _edge_faces(f):
    """Undirected edges of a closed manifold mesh: (lo, hi, face0, face1) arrays."""
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    face_of = np.tile(np.arange(len(f)), 3)
    lo, hi = directed.min(axis=1), directed.max(axis=1)
    order = np.lexsort((hi, lo))
    lo, hi, face_of = lo[order], hi[order], face_of[order]
    return lo[0::2], hi[0::2], face_of[0::2], face_of[1::2]


def _drop_unused(v, f):
    used = np.zeros(len(v), bool)
    used[f.ravel()] = True
    if used.all():
        return v, f
    remap = np.cumsum(used) - 1
    return v[used], remap[f]


def _closed_mesh_fault(v, f, want_euler, volume):
    """None when (v, f) is an oriented closed manifold of one body with the given Euler
    characteristic and a volume within 2% of `volume`; else what is wrong."""
    if len(f) < 4:
        return "fewer than 4 faces"
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    if (np.linalg.norm(cross, axis=1) <= 1e-14).any():
        return "degenerate faces"
    n = len(v)
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    key = directed[:, 0] * n + directed[:, 1]
    rkey = directed[:, 1] * n + directed[:, 0]
    skey = np.sort(key)
    if (np.diff(skey) == 0).any():
        return "an edge used twice in the same direction (non-manifold or flipped)"
    pos = np.searchsorted(skey, rkey)
    pos = np.minimum(pos, len(skey) - 1)
    if not (skey[pos] == rkey).all():
        return "open edges"
    if len(v) - len(directed) // 2 + len(f) != want_euler:
        return "topology changed (pinched vertex or lost handle)"
    if _face_components(f) != 1:
        return "more than one body"
    vol = float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0)
    if abs(vol - volume) > 0.02 * abs(volume):
        return f"volume changed by {100 * (vol - volume) / volume:+.1f}%"
    return None


def _face_components(f):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = int(f.max()) + 1
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n, n))
    return connected_components(graph, directed=False)[0]


def _separate_shared_vertices(vertices, faces, rng, tol=1e-6):
    """Move every vertex that sits on a vertex of an earlier piece a little along its sharpest edge.

    Decimation keeps some vertices of the fine meshes, and neighbours' fine meshes
    share the vertices of their common cut; a scan never samples two fragments at
    the same points. Sliding along the incident edge with the largest dihedral
    angle keeps a vertex on the surface (and on a crease when it is on one).
    """
    from scipy.spatial import cKDTree

    vertices = [np.array(v, np.float64, copy=True) for v in vertices]
    for _round in range(5):
        owner = np.concatenate([np.full(len(v), k) for k, v in enumerate(vertices)])
        local = np.concatenate([np.arange(len(v)) for v in vertices])
        pairs = cKDTree(np.vstack(vertices)).query_pairs(tol, output_type="ndarray")
        if len(pairs) == 0:
            break
        pairs = pairs[owner[pairs[:, 0]] != owner[pairs[:, 1]]]
        if len(pairs) == 0:
            break
        later = np.where(owner[pairs[:, 0]] > owner[pairs[:, 1]], pairs[:, 0], pairs[:, 1])
        later = np.unique(later)
        for k in np.unique(owner[later]):
            _slide_vertices(vertices[k], faces[k], local[later[owner[later] == k]], rng)
    return vertices


def _slide_vertices(v, f, which, rng):
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    # Undirected edges with their two faces -> dihedral angle per edge.
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    face_of = np.tile(np.arange(len(f)), 3)
    lo, hi = directed.min(axis=1), directed.max(axis=1)
    order = np.lexsort((hi, lo))
    lo, hi, face_of = lo[order], hi[order], face_of[order]
    e0, e1 = lo[0::2], hi[0::2]
    cos = np.einsum("ij,ij->i", fn[face_of[0::2]], fn[face_of[1::2]])
    for vid in which:
        sel = np.flatnonzero((e0 == vid) | (e1 == vid))
        incident = np.flatnonzero((f == vid).any(axis=1))
        before = fn[incident]
        for edge in sel[np.argsort(cos[sel])]:  # sharpest first
            other = e1[edge] if e0[edge] == vid else e0[edge]
            old = v[vid].copy()
            v[vid] = old + rng.uniform(0.2, 0.4) * (v[other] - old)
            tri = v[f[incident]]
            after = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            norm = np.linalg.norm(after, axis=1)
            if (norm > 1e-14).all() and (np.einsum("ij,ij->i", after / norm[:, None], before) > 0.5).all():
                break
            v[vid] = old


def _vertex_normals(v, f):
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # area weighted
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


# --- touching pairs ----------------------------------------------------------

def _touching_pairs(vertices, faces):
    """Pairs whose exact surfaces come within CONTACT_DISTANCE over more than
    CONTACT_FRACTION of the smaller one's area; with the contact area of each."""
    from scipy.spatial import cKDTree

    info = []
    for v, f in zip(vertices, faces):
        tri = v[f]
        centres = tri.mean(axis=1)
        areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        reach = float(np.linalg.norm(tri - centres[:, None], axis=2).max())
        info.append((tri, centres, areas, cKDTree(centres), reach, v.min(0), v.max(0)))
    pairs, contact = [], []
    d = CONTACT_DISTANCE
    for i in range(len(info)):
        for j in range(i + 1, len(info)):
            if (info[i][5] > info[j][6] + d).any() or (info[j][5] > info[i][6] + d).any():
                continue
            a_ij = _area_near(info[i], info[j], d)
            a_ji = _area_near(info[j], info[i], d)
            frac = max(a_ij / info[i][2].sum(), a_ji / info[j][2].sum())
            if frac > CONTACT_FRACTION:
                pairs.append((i, j))
                contact.append(0.5 * (a_ij + a_ji))
    return pairs, contact


def _area_near(src, dst, d, k=8):
    """Area of src's faces whose centres lie within d of dst's surface."""
    _, centres, areas, _, _, _, _ = src
    dtri, _, _, dtree, reach, lo, hi = dst
    inside = np.flatnonzero(((centres >= lo - d) & (centres <= hi + d)).all(axis=1))
    if len(inside) == 0:
        return 0.0
    k = min(k, len(dtri))
    dist, idx = dtree.query(centres[inside], k=k, distance_upper_bound=d + reach)
    dist, idx = dist.reshape(len(inside), k), idx.reshape(len(inside), k)
    cand = np.isfinite(dist[:, 0])
    if not cand.any():
        return 0.0
    p = centres[inside[cand]]
    best = np.full(len(p), np.inf)
    for col in range(k):
        ok = np.isfinite(dist[cand, col])
        if not ok.any():
            break
        t = dtri[idx[cand, col][ok]]
        best[ok] = np.minimum(best[ok], _point_triangle_distance(p[ok], t[:, 0], t[:, 1], t[:, 2]))
    return float(areas[inside[cand]][best <= d].sum())


def _point_triangle_distance(p, a, b, c):
    """Distance from points p to triangles (a, b, c), row by row (Ericson, Real-Time Collision Detection 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    bp = p - b
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    cp = p - c
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = vb / denom
        w = vc / denom
        closest = a + v[:, None] * ab + w[:, None] * ac  # inside the face
        # edges
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    conds = [
        (d1 <= 0) & (d2 <= 0), (d3 >= 0) & (d4 <= d3), (d6 >= 0) & (d5 <= d6),
        (vc <= 0) & (d1 >= 0) & (d3 <= 0), (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0),
    ]
    choices = [a, b, c, a + t_ab[:, None] * ab, a + t_ac[:, None] * ac, b + t_bc[:, None] * (c - b)]
    result = closest
    for cond, choice in zip(reversed(conds), reversed(choices)):
        result = np.where(cond[:, None], choice, result)
    return np.linalg.norm(p - result, axis=1)


def _dot(x, y):
    return np.einsum("ij,ij->i", x, y)


# --- poses -----------------------------------------------------------------

def _random_unit(rng, dim=3):
    while True:
        x = rng.normal(size=dim)
        n = np.linalg.norm(x)
        if n > 1e-6:
            return x / n


def _frame(normal):
    """Two unit vectors completing `normal` to a right-handed orthonormal frame (u, w, normal)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(helper, normal)
    u /= np.linalg.norm(u)
    return u, np.cross(normal, u)


def _weighted_quantile(values, weights, q):
    order = np.argsort(values)
    cum = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cum, q * cum[-1])])


def _random_rotation(rng):
    q = _random_unit(rng, 4)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _random_placement(vertices, rng):
    """A rigid 4x4 taking object-frame points to a random pose: a random rotation about
    the piece's centroid, then the centroid moved to a random point of [-2, 2]^3."""
    rot = _random_rotation(rng)
    centroid = vertices.mean(axis=0)
    target = rng.uniform(-SCATTER_RANGE, SCATTER_RANGE, 3)
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = target - rot @ centroid
    return m


def _invert_rigid(m):
    inv = np.eye(4)
    inv[:3, :3] = m[:3, :3].T
    inv[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return inv


# --- progress --------------------------------------------------------------

class _NoBar:
    def update(self, n=1):
        pass

    def close(self):
        pass


def _progress_bar(total, show, desc):
    if not show:
        return _NoBar()
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="cut", file=sys.stderr, leave=False)


# --- CLI -------------------------------------------------------------------

def cli_add_arguments(parser) -> None:
    parser.add_argument("out", metavar="OUT", help="output directory (fragments/, truth.json, labels.npz)")
    parser.add_argument("--shape", default="vase",
                        help="vase, torso, slab, or the path of a closed mesh file; a comma list cycles over --objects "
                             "(default: vase)")
    parser.add_argument("--pieces", type=int, default=2, help="number of fragments per object (default: 2)")
    parser.add_argument("--seed", type=int, default=0, help="random seed; object k uses seed + k (default: 0)")
    parser.add_argument("--faces", type=int, default=4000,
                        help="about this many faces per fragment; vertices are about half (default: 4000)")
    parser.add_argument("--noise", type=float, default=0.0,
                        help="scanner noise along normals, standard deviation as a fraction of the object size "
                             "(default: 0)")
    parser.add_argument("--roughness", type=float, default=0.02,
                        help="RMS height of the fracture surfaces as a fraction of the object size (default: 0.02)")
    parser.add_argument("--no-scatter", action="store_true", help="leave the pieces in place (truth poses = identity)")
    parser.add_argument("--objects", type=int, default=1,
                        help="break this many objects into the same OUT, named o0_..., o1_... (default: 1)")
    parser.add_argument("--prefix", default="", help="prefix of the fragment names; an existing OUT with another "
                                                     "prefix gets this object added (default: none)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar or summary")


def cli_main(args) -> int:
    from .errors import CliError

    if args.objects < 1:
        raise CliError(f"--objects must be at least 1, got {args.objects}")
    shapes = [args.shape] if Path(args.shape).exists() else [s.strip() for s in args.shape.split(",") if s.strip()]
    if not shapes:
        raise CliError("--shape is empty")
    results, prefixes = [], []
    start = time.perf_counter()
    try:
        for k in range(args.objects):
            results.append(generate(shapes[k % len(shapes)], pieces=args.pieces, seed=args.seed + k, faces=args.faces,
                                    noise=args.noise, roughness=args.roughness, scatter=not args.no_scatter,
                                    progress=None if not args.quiet else False))
            prefixes.append(args.prefix if args.objects == 1 else f"{args.prefix}o{k}_")
        write_many(results, args.out, prefixes)
    except FragmentError:
        raise
    except ValueError as exc:
        raise CliError(str(exc)) from None
    if not args.quiet:
        n = sum(len(r.fragments) for r in results)
        pairs = sum(len(r.touching) for r in results)
        print(f"wrote {n} fragments of {len(results)} object(s) to {Path(args.out) / 'fragments'}, "
              f"{pairs} touching pairs, truth in {Path(args.out) / 'truth.json'} "
              f"({time.perf_counter() - start:.2f} s)", file=sys.stderr)
    return 0
