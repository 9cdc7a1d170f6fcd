"""Issue 15: a thin board's break leaves a turn of the fit loose; the skin across the seam holds it."""
import numpy as np
import pytest

from relicgpu.backends import resolve
from relicgpu.cloud.points import local_pca
from relicgpu.pair import seam
from relicgpu.pair.icp import axis_rotation, rotation_angle_deg

BEND = 0.28  # a roof tile's bend along its length (relicgpu.synth's slab)


def _break(y, z):
    """Where the rough break crosses the board (x, before the bend) at (y, z)."""
    return 0.02 * np.sin(9 * y) + 0.012 * np.sin(31 * z + 5 * y) + 0.006 * np.sin(47 * y + 13 * z)


def _oriented(points, hint):
    normals = local_pca(points, 12)[1][:, :, 0]
    return normals * np.where(np.einsum("ij,ij->i", normals, hint) < 0, -1.0, 1.0)[:, None]


def _board(rng, side, n=1200, noise=0.0005):
    """One piece of a bent board (1 x 0.66 x 0.08) broken across its length: the piece left of the
    break (side -1) or right of it (+1), as ((points, normals) of its skin, its break's points and
    normals)."""
    def warp(p):
        return p + np.outer(BEND * p[:, 0] ** 2, [0.0, 0.0, 1.0])

    skin = []
    for face in (1.0, -1.0):  # broad faces only: the edges are far from the seam
        p = np.column_stack([rng.uniform(-0.5, 0.5, n), rng.uniform(-0.33, 0.33, n), np.full(n, 0.04 * face)])
        p = p[side * (p[:, 0] - _break(p[:, 1], p[:, 2])) > 0]
        skin.append((warp(p), face))
    y, z = rng.uniform(-0.33, 0.33, n // 2), rng.uniform(-0.04, 0.04, n // 2)
    fracture = warp(np.column_stack([_break(y, z), y, z]))
    pts = np.vstack([p for p, _ in skin])
    hint = np.vstack([np.tile([0.0, 0.0, f], (len(p), 1)) for p, f in skin])
    pts = pts + rng.normal(size=pts.shape) * noise
    fracture = fracture + rng.normal(size=fracture.shape) * noise
    return (pts, _oriented(pts, hint)), (fracture, _oriented(fracture, np.tile([-side, 0.0, 0.0], (len(fracture), 1))))


def _fold(degrees):
    """A turn about the board's length axis through the break (y: the band's long direction)."""
    out = np.eye(4)
    out[:3, :3] = axis_rotation(np.array([0.0, 1.0, 0.0]), np.radians(degrees))
    return out


def test_a_narrow_break_is_loose_and_a_square_one_is_not():
    rng = np.random.default_rng(0)
    be = resolve("numpy")
    _, (frac_a, normals_a) = _board(rng, -1)
    _, (frac_b, _) = _board(rng, 1)
    loose = seam.looseness(frac_b, frac_a, normals_a, np.eye(4), 0.03, be.nearest_index(frac_a))
    assert loose < seam.LOOSE
    # a square break, its relief four times as deep: every direction is held
    y, z = rng.uniform(-0.33, 0.33, 800), rng.uniform(-0.33, 0.33, 800)
    square = np.column_stack([4 * _break(y, z), y, z])
    normals = _oriented(square, np.tile([1.0, 0.0, 0.0], (len(square), 1)))
    assert seam.looseness(square, square, normals, np.eye(4), 0.03, be.nearest_index(square)) > 5 * seam.LOOSE


@pytest.mark.parametrize("degrees", [3.0, -2.5])
def test_the_skin_across_the_seam_unfolds_a_loose_fit(degrees):
    rng = np.random.default_rng(1)
    be = resolve("numpy")
    skin_a, (frac_a, normals_a) = _board(rng, -1)
    skin_b, (frac_b, _) = _board(rng, 1)
    start = _fold(degrees)  # the truth is the identity
    polished, held = seam.seam_polish(frac_a, normals_a, frac_b, skin_a, skin_b, start, 0.03, 1.0,
                                      be.nearest_index(frac_a))
    assert held >= 20
    assert rotation_angle_deg(polished[:3, :3]) < 0.5


def test_skin_that_does_not_continue_holds_nothing():
    rng = np.random.default_rng(2)
    skin_a, _ = _board(rng, -1)
    skin_b, _ = _board(rng, 1)
    # b's skin lifted off a's surface by twenty noise levels: not its continuation
    lifted = skin_b[0] + [0.0, 0.0, 0.01]
    patches = seam.seam_surfaces(*skin_a, lifted, skin_b[1], seam.NEAR, seam.REACH, seam.MAX_FIT)
    assert len(patches) == 0
    patches = seam.seam_surfaces(*skin_a, *skin_b, seam.NEAR, seam.REACH, seam.MAX_FIT)
    assert len(patches) >= 20


def _quadric_reference(points, normals):
    """One quadric height field over (K, 3) points along their mean normal, by numpy.linalg.lstsq."""
    centre = points.mean(0)
    m = normals.mean(0) / np.linalg.norm(normals.mean(0))
    t1 = np.cross(m, [1.0, 0.0, 0.0]) if abs(m[0]) < 0.9 else np.cross(m, [0.0, 1.0, 0.0])
    t1 /= np.linalg.norm(t1)
    axes = np.stack([t1, np.cross(m, t1), m])
    u, v, h = ((points - centre) @ axes.T).T
    design = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], 1)
    coef = np.linalg.lstsq(design, h, rcond=None)[0]
    return centre, axes, coef, float(np.sqrt(np.mean((design @ coef - h) ** 2)))


def test_the_batched_quadrics_fit_each_row_as_least_squares_does():
    """`seam._quadrics` fits every row's masked points at once (the rows' points one after another):
    each row as `numpy.linalg.lstsq` fits it alone, on random patches and on adversarial ones (collinear points, whose fit has no unique
    solution: the minimum-norm one; a patch facing along x, whose frame is taken from y; a narrow
    strip; a small patch far from the origin)."""
    rng = np.random.default_rng(3)
    rows, width = 40, 30
    points = rng.normal(size=(rows, width, 3)) * [1.0, 1.0, 0.05]
    normals = np.array([0.0, 0.0, 1.0]) + rng.normal(size=(rows, width, 3)) * 0.1
    mask = rng.random((rows, width)) < 0.6
    mask[:, :seam.MIN_FIT] = True
    points[0, :, 1] = 0.0  # collinear in the plane, flat across it
    points[0, :, 2] = 0.0
    points[1] = points[1][:, ::-1]
    normals[1] = normals[1][:, ::-1]
    points[2, :, 1] *= 1e-3  # a strip a thousandth as wide as it is long
    points[3] = points[3] * 1e-4 + 1e3  # far from the origin, small
    count = mask.sum(1)
    centre, axes, coef, fit = seam._quadrics(points[mask], normals[mask], np.cumsum(count) - count)
    for k in range(rows):
        c, a, q, f = _quadric_reference(points[k][mask[k]], normals[k][mask[k]])
        assert np.allclose(centre[k], c, atol=1e-12) and np.allclose(axes[k], a, atol=1e-12)
        assert np.allclose(coef[k], q, atol=1e-9) and abs(fit[k] - f) < 1e-9, k
