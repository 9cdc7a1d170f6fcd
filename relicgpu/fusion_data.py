"""The training data of the fusion MLP (see relicgpu.fusion_train): touching pairs of
synthetic objects (relicgpu.synth), both fragments prepared at the pair's scale, with the
fusion inputs of their contours and the true correspondences of b's contour points on a's
(`build_pairs`, cached on disk by the specs, the parameters and the code that makes them)."""
from __future__ import annotations

import hashlib
import json
import pickle
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import pair, synth, topology
from . import params as params_module
from .backends import numpy as numpy_backend
from .pair import fusion as fusion_mod
from .pair.features import dimensionless
from .pair.prepare import prepare
from .params import Params

SHAPES = ("vase", "torso", "slab")


TRUE_WITHIN = 0.01  # a correspondence is true within this share of the pair scale


CACHE_VERSION = 1


@dataclass(frozen=True)
class ObjectSpec:
    shape: str
    pieces: int
    seed: int
    noise: float


@dataclass(eq=False)
class PairData:
    """One touching pair of a synthetic object, prepared at the pair scale."""
    spec: ObjectSpec
    i: int  # fragment a
    j: int  # fragment b
    scale: float
    prepared_a: object  # relicgpu.pair.prepare.Prepared
    prepared_b: object
    truth: np.ndarray  # (4,4) carrying b's file coordinates onto a's
    inputs_a: list  # per contour of a: (N,8) fusion inputs [g, f]
    inputs_b: list
    moved_b: list  # per contour of b: (N,3) points moved onto a by the truth
    corr: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), np.int64))  # (K,4) [ca, ia, cb, ib]


def object_specs(count: int, seed: int, shapes=SHAPES, pieces=(2, 3, 4), noises=(0.0, 0.0005, 0.001)) -> list[ObjectSpec]:
    """`count` synthetic objects cycling through the shapes, pieces and noise levels; the
    synth seeds start at `seed` (keep training, validation and benchmark ranges apart)."""
    out = []
    for k in range(count):  # every combination of shape, noise and pieces within the first few
        out.append(ObjectSpec(shapes[k % len(shapes)], int(pieces[(k // (len(shapes) * len(noises))) % len(pieces)]),
                              seed + k, float(noises[(k // len(shapes)) % len(noises)])))
    return out


def contour_inputs(contour, scale: float, params: Params) -> np.ndarray:
    """The fusion inputs of a prepared contour (the same f the pipeline fuses)."""
    f = dimensionless(contour.features, params.contour_step * scale * params.feature_stride)
    return fusion_mod.fusion_inputs(f)


def _move(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ t[:3, :3].T + t[:3, 3]


def true_correspondences(points_a: list, moved_b: list, within: float) -> np.ndarray:
    """(K,4) [ca, ia, cb, ib]: each point of b's contours (moved onto a) with the nearest
    point of a's contours, when that is within `within`."""
    from scipy.spatial import cKDTree

    if not points_a or not moved_b:
        return np.zeros((0, 4), np.int64)
    pa = np.concatenate(points_a)
    owner = np.concatenate([np.stack([np.full(len(p), c), np.arange(len(p))], 1) for c, p in enumerate(points_a)])
    out = []
    tree = cKDTree(pa)
    for cb, q in enumerate(moved_b):
        d, k = tree.query(q)
        ok = np.flatnonzero(d <= within)
        out.append(np.stack([owner[k[ok], 0], owner[k[ok], 1], np.full(len(ok), cb), ok], 1))
    return np.concatenate(out).astype(np.int64) if out else np.zeros((0, 4), np.int64)


_DATA_MODULES = (synth, pair, topology, params_module, numpy_backend)


def _code_hash() -> str:
    """Hash of the code that makes the cached pairs (a package: all its modules): a change to
    it makes them again."""
    h = hashlib.sha256()
    for mod in _DATA_MODULES:
        p = Path(mod.__file__)
        for f in sorted(p.parent.glob("*.py")) if p.name == "__init__.py" else [p]:
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def build_pairs(specs: list[ObjectSpec], params: Params | None = None, faces: int = 4000,
                pairs_per_object: int = 2, progress: bool = True, cache_dir=None, desc: str = "pairs") -> list[PairData]:
    """Generate the objects, prepare up to `pairs_per_object` touching pairs of each (numpy
    backend) and find their true correspondences. Cached under `cache_dir` (default: the
    system temp dir) by the specs, the parameters and the code that makes them."""
    from tqdm import tqdm

    params = params or Params()
    key = json.dumps([CACHE_VERSION, _code_hash(), [s.__dict__ for s in specs], faces, pairs_per_object,
                      {k: v for k, v in params.to_dict().items() if k != "fusion_weights"}], sort_keys=True)
    cache = Path(cache_dir or tempfile.gettempdir()) / "relicgpu-fusion-cache"
    path = cache / (hashlib.sha256(key.encode()).hexdigest()[:24] + ".pkl")
    if path.exists():
        try:
            with open(path, "rb") as fh:
                return pickle.load(fh)
        except Exception:  # a stale or broken cache file is made again
            pass
    plain = params.with_(fusion_weights=None)
    out = []
    for spec in tqdm(specs, desc=desc, disable=not progress, file=sys.stderr):
        r = synth.generate(spec.shape, pieces=spec.pieces, seed=spec.seed, faces=faces, noise=spec.noise,
                           progress=False)
        # spread the chosen pairs over the object's touching list
        chosen = r.touching[:: max(1, len(r.touching) // pairs_per_object)][:pairs_per_object]
        for i, j in chosen:
            a, b = r.fragments[i], r.fragments[j]
            scale = 0.5 * (a.size + b.size)
            pa = prepare(a, plain, "numpy", scale=scale)
            pb = prepare(b, plain, "numpy", scale=scale)
            truth = np.linalg.inv(r.poses[i]) @ r.poses[j]
            moved = [_move(truth, c.points) for c in pb.contours]
            corr = true_correspondences([c.points for c in pa.contours], moved, TRUE_WITHIN * scale)
            out.append(PairData(spec, i, j, scale, pa, pb, truth,
                                [contour_inputs(c, scale, plain) for c in pa.contours],
                                [contour_inputs(c, scale, plain) for c in pb.contours], moved, corr))
    cache.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    with open(tmp, "wb") as fh:
        pickle.dump(out, fh, protocol=pickle.HIGHEST_PROTOCOL)
    tmp.replace(path)
    return out
