"""Normals of a thin wall's cloud scanned without them (`relicgpu.cloud.wall_normals`)."""
from __future__ import annotations

import numpy as np

from relicgpu.cloud.wall_normals import wall_normals


def board_cloud(thickness: float, n: int = 2500, seed: int = 0):
    """(n, 3) points drawn evenly by area off a 0.5 x 1 board `thickness` thick, their (n, 3) true
    normals and (n,) True where a point lies on one of the two broad faces."""
    rng = np.random.default_rng(seed)
    size = np.array([0.5, 1.0, thickness])
    # the six sides: the axis each faces along and its sign; areas of the other two extents
    sides = [(axis, sign) for axis in (2, 0, 1) for sign in (1, -1)]
    area = np.array([np.prod(np.delete(size, axis)) for axis, _ in sides])
    which = rng.choice(len(sides), n, p=area / area.sum())
    points = rng.random((n, 3)) * size
    normals = np.zeros((n, 3))
    for i, (axis, sign) in enumerate(sides):
        m = which == i
        points[m, axis] = size[axis] if sign > 0 else 0.0
        normals[m, axis] = sign
    return points, normals, which < 2


def test_a_board_two_spacings_thick_gets_each_face_and_its_narrow_sides():
    points, truth, broad = board_cloud(0.02)  # the median spacing is about 0.0095
    normals = wall_normals(points)
    assert normals.shape == points.shape
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)
    agree = np.einsum("ij,ij->i", normals, truth)
    inside = broad & np.all((points[:, :2] > 0.1) & (points[:, :2] < np.array([0.4, 0.9])), axis=1)
    # each broad face's points take their own face's side (a plane through both faces has no side)
    assert np.mean(agree[inside] > np.cos(np.radians(10))) > 0.97
    # the narrow sides (the strip a break leaves) are told from the face rows beside them
    strip = np.abs(normals[:, 2]) < 0.5
    assert np.mean(strip[~broad]) > 0.5
    assert np.mean(~broad[strip]) > 0.75
    assert np.mean(agree[strip & ~broad] > np.cos(np.radians(30))) > 0.8


def test_a_single_sheet_has_no_strip_and_a_tiny_cloud_no_fault():
    rng = np.random.default_rng(1)
    # one layer (a thick piece's skin): no point lies between two faces, so none is read as strip
    flat = np.c_[rng.random((400, 2)), 1e-4 * rng.normal(size=400)]
    assert np.all(np.abs(wall_normals(flat)[:, 2]) > 0.99)
    few = wall_normals(rng.random((5, 3)))
    assert few.shape == (5, 3)
    np.testing.assert_allclose(np.linalg.norm(few, axis=1), 1.0, atol=1e-9)
