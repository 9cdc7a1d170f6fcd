"""The fine stage of a pair's search: the starts that rank best, refined by ICP (Alg. 5) and a
point-to-plane polish, each on the pairs of a's and b's fracture samples (`icp`).

Between two fine meshes only pairs whose normals face each other are used (`facing_test`,
`Params.fine_facing`): a rescanned break's skin beside it, read as break, lies by the partner's
skin facing the same way and folds a thin band's fit about its length (docs/benchmarks.md, "The
fine stage on facing pairs"; `scripts/bench_fine.py`)."""
from __future__ import annotations

import numpy as np

from ..params import Params
from .icp import batched_icp, refine_point_to_plane
from .prepare import Prepared


def fine_stage(pa: Prepared, pb: Prepared, starts: np.ndarray, params: Params, be, scale: float, index,
               at_most: int) -> tuple[np.ndarray, np.ndarray]:
    """The fine stage of a pair's search: ICP of all (H, 4, 4) starts carrying b onto a together
    (one nearest-neighbour launch a round; `index` is a's fracture sample's), then the point-to-plane
    polish of the `at_most` touching most. Returns their (K, 4, 4) poses and the (K,) indices of
    the starts they came from, best-touching first."""
    facing = facing_test(pa, pb, params, scale)
    contact = params.contact_distance * scale
    fine, share = batched_icp(pb.sample.fracture, pa.sample.fracture, starts, be, params.icp_iterations,
                              params.icp_reject * scale, contact, params.icp_tolerance * scale, params.icp_trim, index,
                              pb.sample.weights(), pa.sample.weights(), facing)
    best_first = np.argsort(-share, kind="stable")[:at_most]
    polished = refine_point_to_plane(pb.sample.fracture, pa.sample.fracture, pa.sample.fracture_normals,
                                     fine[best_first], be, params.plane_iterations, contact, index,
                                     pb.sample.weights(), pa.sample.weights(), facing)
    return polished, best_first


def facing_test(pa: Prepared, pb: Prepared, params: Params, scale: float) -> tuple | None:
    """The fine stage's normal test (`icp.batched_icp`'s `facing`) where both are meshes whose median
    edge is under `Params.facing_edge` of the scale, else None. On a fine mesh the fracture sample's
    vertex normals are the break's, and two sides of one break face each other; a rescanned
    break's skin beside it, read as break, lies near the partner's skin facing the same way and
    held the fit of a thin wall's band a few degrees off. On a coarse mesh most fracture vertices
    lie on the rim, their normals the mean of skin and break, and the test leaves too few pairs."""
    if params.fine_facing is None or not all(_fine_mesh(p, params.facing_edge * scale) for p in (pa, pb)):
        return None
    return pb.sample.fracture_normals, pa.sample.fracture_normals, params.fine_facing


def _fine_mesh(p: Prepared, edge: float) -> bool:
    """Whether the fragment is a mesh (a cloud's faces are empty) whose median edge is under `edge`."""
    v, faces = p.fragment.vertices, p.fragment.faces
    return len(faces) > 0 and float(np.median(np.linalg.norm(v[faces[:, 0]] - v[faces[:, 1]], axis=1))) < edge
