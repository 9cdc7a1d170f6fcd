"""The known answer: `SynthResult`, which pieces touch (and over what area), and the files
`write` / `write_many` put on disk and `read_truth` / `load_labels` read back (see the
package docstring)."""
from __future__ import annotations

import io as _io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..io.files import atomic_write_bytes, atomic_write_json, write_mesh
from ..io.fragment import Fragment, FragmentError

TRUTH_VERSION = 1
# Two pieces touch when more than CONTACT_FRACTION of the surface of one lies
# within CONTACT_DISTANCE of the other (measured on the exact, noise-free pieces).
CONTACT_DISTANCE = 0.005
CONTACT_FRACTION = 0.01


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
