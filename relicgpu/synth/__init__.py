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

Modules: `shapes` (the solids), `fracture` (the rough cuts), `scanning` (each
piece remeshed as a scan, its pose), `truth` (SynthResult, contacts, the files),
`generator` (`generate`), `command` (`relicgpu synth`), and `corpus` (an
independent generator's families, the realdata sets).
"""
from __future__ import annotations

from .generator import generate
from .shapes import SHAPES, make_shape
from .truth import (CONTACT_DISTANCE, CONTACT_FRACTION, TRUTH_VERSION, SynthResult, load_labels, read_truth, write,
                    write_many)

__all__ = ["SHAPES", "TRUTH_VERSION", "CONTACT_DISTANCE", "CONTACT_FRACTION", "SynthResult", "generate", "make_shape",
           "write", "write_many", "read_truth", "load_labels"]
