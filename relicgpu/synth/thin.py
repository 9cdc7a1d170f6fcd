"""Thin objects broken in two: bookshelves of thin boards and a potted plant (issue 15).

Issue 15's hidden clouds are two-piece breaks of a bookshelf and a plant. These are made here
the same way, so that the thin-object figures of `docs/benchmarks.md` can be measured again
(`scripts/bench_clouds.py --source thin`). A family is an object crossed with a cut:

objects (`OBJECTS`)
    shelf02  a bookshelf of boards 0.02 thick (sides, top, bottom, back, three shelves;
             0.8 wide, 0.3 deep, 1.0 high)
    shelf04  the same with boards 0.04 thick
    plant    a pot with soil, a stem and six thin leaves (leaves 0.008 thick before scaling),
             scaled to a bounding-box diagonal of 1
cuts (`CUTS`)
    flat     a plane
    smooth   `corpus`'s smooth height field (a few long waves)
    rough    `corpus`'s rough height field (fractal octaves, relief about 1% of the size)

Each cut goes through the middle fifth of the object with a random normal and is drawn again
until both halves are single bodies of at least a fifth of the volume. The halves are the exact
boolean meshes (labels: faces not from the object are fracture), scattered to random poses.
"""
from __future__ import annotations

import zlib

import numpy as np

from ..io.fragment import Fragment
from .corpus import _arrays, _cutter, _height_function
from .scanning import _invert_rigid, _random_placement
from .truth import SynthResult, _touching_pairs

OBJECTS = ("shelf02", "shelf04", "plant")
CUTS = ("flat", "smooth", "rough")
FAMILIES = tuple(f"{o}-{c}" for o in OBJECTS for c in CUTS)
CUT_SPACING = 0.01  # the cutter's grid, object units
MIN_HALF = 0.2  # a half below this share of the object's volume makes the cut be drawn again
MAX_ATTEMPTS = 1000


def generate(family: str, seed: int = 0, scatter: bool = True) -> SynthResult:
    """Cut one object of `family` ("<object>-<cut>", one of `FAMILIES`) in two.

    Returns
    -------
    SynthResult
        two fragments (V_i, 3) / (F_i, 3); poses (4, 4) carrying file coordinates into the object
        frame; touching [(0, 1)] where the halves touch; fracture_faces (F_i,) bool;
        params["size"] the object's size (the largest side of its bounding box).
    """
    name, _, cut = family.partition("-")
    if name not in OBJECTS or cut not in CUTS:
        raise ValueError(f"unknown thin family {family!r}; choose from {', '.join(FAMILIES)}")
    shape_rng, cut_rng, scatter_rng = (np.random.default_rng(s) for s in
                                       np.random.SeedSequence([int(seed), zlib.crc32(family.encode())]).spawn(3))
    solid = (plant(shape_rng) if name == "plant" else bookshelf(0.02 if name == "shelf02" else 0.04)).as_original()
    parts = cut_in_two(solid, cut, cut_rng)
    exact = [_arrays(p, solid.original_id()) for p in parts]
    touching, contact = _touching_pairs([e[0] for e in exact], [e[1] for e in exact])
    lo, hi = np.split(np.array(solid.bounding_box()), 2)
    fragments, poses = [], []
    for i, (v, f, _) in enumerate(exact):
        place = _random_placement(v, scatter_rng) if scatter else np.eye(4)
        fragments.append(Fragment(f"frag_{i:02d}", v @ place[:3, :3].T + place[:3, 3], f.astype(np.int32)))
        poses.append(_invert_rigid(place))
    params = {"family": family, "pieces": 2, "seed": int(seed), "size": float((hi - lo).max()),
              "generator": "relicgpu.synth.thin"}
    return SynthResult(fragments, poses, touching, family, int(seed), params,
                       fracture_faces=[e[2] for e in exact], contact_areas=contact,
                       object_volume=float(solid.volume()), piece_volumes=[float(p.volume()) for p in parts])


def bookshelf(thickness: float):
    """A bookshelf of boards `thickness` thick (a manifold3d.Manifold, 0.8 x 0.3 x 1.0, corner at 0)."""
    import manifold3d

    def board(lo, hi):
        return manifold3d.Manifold.cube(list(np.subtract(hi, lo))).translate(list(lo))

    w, d, h, t = 0.8, 0.3, 1.0, thickness
    solid = board([0, 0, 0], [t, d, h])
    for lo, hi in (([w - t, 0, 0], [w, d, h]), ([0, 0, 0], [w, d, t]), ([0, 0, h - t], [w, d, h]),
                   ([0, d - t, 0], [w, d, h]), ([0, 0, 0.3], [w, d, 0.3 + t]), ([0, 0, 0.55], [w, d, 0.55 + t]),
                   ([0, 0, 0.75], [w, d, 0.75 + t])):
        solid = solid + board(lo, hi)
    return solid


def plant(rng: np.random.Generator):
    """A potted plant (a manifold3d.Manifold centred, bounding-box diagonal 1): a pot with soil, a stem
    and six thin leaves turned at random."""
    import manifold3d as m3

    pot = m3.Manifold.cylinder(0.25, 0.14, 0.17, 48) - m3.Manifold.cylinder(0.25, 0.125, 0.155, 48).translate(
        [0, 0, 0.02])
    solid = pot + m3.Manifold.cylinder(0.02, 0.15, 0.15, 48).translate([0, 0, 0.19])
    solid = solid + m3.Manifold.cylinder(0.55, 0.012, 0.008, 16).translate([0, 0, 0.2])
    for i in range(6):
        leaf = m3.Manifold.sphere(1.0, 24).scale([0.14, 0.05, 0.008]).translate([0.13, 0, 0])
        leaf = leaf.rotate([rng.uniform(-25, 25), 0, 0]).rotate([0, -rng.uniform(10, 35), 0])
        solid = solid + leaf.rotate([0, 0, 360 * i / 6 + rng.uniform(-20, 20)]).translate([0, 0, 0.35 + 0.07 * i])
    lo, hi = np.split(np.array(solid.bounding_box()), 2)
    return solid.translate(list(-(lo + hi) / 2)).scale([1 / float(np.linalg.norm(hi - lo))] * 3)


def cut_in_two(solid, cut: str, rng: np.random.Generator) -> tuple:
    """`solid` cut by a `cut` surface (one of `CUTS`) into two single bodies, each at least `MIN_HALF`
    of its volume: (the part above the surface, the part below)."""
    lo, hi = np.split(np.array(solid.bounding_box()), 2)
    for _ in range(MAX_ATTEMPTS):
        point = 0.5 * (lo + hi) + rng.uniform(-0.2, 0.2, 3) * (hi - lo)
        normal = rng.normal(size=3)
        normal /= np.linalg.norm(normal)
        radius = 0.5 * float(np.linalg.norm(hi - lo)) + float(np.linalg.norm(point - 0.5 * (lo + hi))) + 0.05
        if cut == "flat":
            cutter = _cutter(point, normal, radius, radius, lambda a, b: np.zeros_like(a))
        else:
            cutter = _cutter(point, normal, radius, CUT_SPACING, _height_function(cut, rng, CUT_SPACING))
        parts = (solid ^ cutter, solid - cutter)
        if all(len(p.decompose()) == 1 and p.volume() > MIN_HALF * solid.volume() for p in parts):
            return parts
    raise RuntimeError(f"thin: no {cut} cut leaves two single bodies in {MAX_ATTEMPTS} attempts")
