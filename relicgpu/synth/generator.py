"""`generate`: a solid made, broken, remeshed piece by piece, noised and scattered, with
its known answer (a `SynthResult`)."""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

from ..io.fragment import Fragment
from .fracture import FBM_WAVELENGTH, _fracture, _manifold_arrays
from .scanning import (_clean_slivers, _closed_mesh_fault, _invert_rigid, _random_placement,
                       _separate_shared_vertices, _vertex_normals)
from .shapes import SHAPES, make_shape
from .truth import CONTACT_DISTANCE, CONTACT_FRACTION, SynthResult, _touching_pairs

# Per built-in shape, measured over seeds 0-2 and 2/5/10 pieces, to choose the sampling
# density before building: surface area after normalising; fracture area (both sides)
# of K pieces / (K - 1)^0.75; and triangles x spacing^2 / area on the original and on
# the fracture surfaces after the sliver clean-up (2 on a plain grid).
_AREA_GUESS = {"vase": (1.55, 0.12, 2.25, 3.1), "torso": (0.84, 0.27, 2.2, 2.25), "slab": (1.11, 0.13, 2.1, 2.75)}
_AREA_GUESS_FILE = (None, 0.2, 2.2, 2.75)


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
