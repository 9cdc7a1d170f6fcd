"""Family 1 (face normals, edge angles): every backend against the float64 reference.

Tolerances. The kernels take float32 vertices shifted to their bounding-box
centre, so a coordinate is off by up to 2^-24 * L/2 (L: the mesh's bounding-box
diagonal) and an edge vector by about 1e-7 * L. With e the face's longest edge
and a_ref its float64 area, that gives 10x margin under:
  areas   : |a - a_ref| <= 1e-6 * L * e + 1e-6 * a_ref
  normals : |n - n_ref| <= 1e-6 * L * e / a_ref + 1e-6    (faces with a_ref > 0)
            exactly zero where a_ref is exactly zero (repeated or collinear grid points)
  angles  : |angle - angle_ref| <= 1e-5 rad (float32 unit normals); exactly 0 next to
            a zero-area face
"""
from __future__ import annotations

import numpy as np
import pytest

from relicgpu.backends import numpy as ref


def _edge_faces(faces: np.ndarray) -> np.ndarray:
    """(E,2) faces sharing each interior edge; boundary edges (one face) are left out."""
    f = np.asarray(faces, np.int64)
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    owner = np.tile(np.arange(len(f)), 3)
    key = np.sort(edges, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, owner = key[order], owner[order]
    same = np.all(key[1:] == key[:-1], axis=1)
    return np.stack([owner[:-1][same], owner[1:][same]], axis=1)


def _grid_mesh(nx: int, ny: int, rng, offset=0.0):
    """An open height-field sheet: boundary edges all round, faces of varied slope."""
    x, y = np.meshgrid(np.linspace(0, 1, nx), np.linspace(0, 1, ny), indexing="ij")
    z = 0.05 * np.sin(7 * x) * np.cos(5 * y) + 0.002 * rng.random(x.shape)
    v = np.stack([x.ravel(), y.ravel(), z.ravel()], 1) + offset
    i = np.arange(nx - 1)[:, None] * ny + np.arange(ny - 1)[None, :]
    i = i.ravel()
    f = np.concatenate([np.stack([i, i + ny, i + 1], 1), np.stack([i + 1, i + ny, i + ny + 1], 1)])
    return v, f


def _check_normals(v, f, n, a, n_ref, a_ref):
    p = v[f]
    edge = np.sqrt(np.max([np.sum((p[:, i] - p[:, (i + 1) % 3]) ** 2, 1) for i in range(3)], axis=0))
    size = np.linalg.norm(v.max(0) - v.min(0))
    assert n.shape == n_ref.shape and a.shape == a_ref.shape
    assert n.dtype == np.float64 and a.dtype == np.float64
    assert np.all(np.abs(a - a_ref) <= 1e-6 * size * edge + 1e-6 * a_ref)
    pos = a_ref > 0
    err = np.linalg.norm(n[pos] - n_ref[pos], axis=1)
    assert np.all(err <= 1e-6 * size * edge[pos] / a_ref[pos] + 1e-6)
    zero = a_ref == 0
    assert np.all(n[zero] == 0) and np.all(a[zero] == 0)


# --- the reference against hand-worked cases --------------------------------------

def test_reference_face_normals_by_hand():
    v = np.array([[0, 0, 0], [2, 0, 0], [0, 3, 0], [1, 1, 1], [4, 4, 4]], float)
    f = np.array([[0, 1, 2], [0, 2, 1], [0, 3, 4], [1, 1, 2]])
    n, a = ref.face_normals(v, f)
    np.testing.assert_allclose(n[0], [0, 0, 1])
    np.testing.assert_allclose(n[1], [0, 0, -1])
    assert a[0] == pytest.approx(3.0) and a[1] == pytest.approx(3.0)
    assert np.all(n[2] == 0) and a[2] == 0  # collinear
    assert np.all(n[3] == 0) and a[3] == 0  # repeated vertex


def test_reference_edge_angles_by_hand():
    n = np.array([[0, 0, 1], [0, 1, 0], [0, 0, -1], [0, 0, 1], [0, 0, 0]], float)
    e = np.array([[0, 1], [0, 2], [0, 3], [0, 4]])
    np.testing.assert_allclose(ref.edge_angles(n, e), [np.pi / 2, np.pi, 0, 0], atol=1e-15)


# --- every backend against the reference --------------------------------------------

def test_face_normals_random_far_from_origin(backend):
    rng = np.random.default_rng()
    v = rng.random((3000, 3)) * 10 + 1000.0
    f = rng.integers(0, len(v), (6000, 3))
    # adversarial faces: repeated vertices, exactly collinear points, a sliver
    v[:3] = [[1000, 1000, 1000], [1001, 1001, 1001], [1003, 1003, 1003]]
    v[3:6] = [[1000, 1000, 1000], [1000.5, 1000, 1000], [1001, 1000, 1e-9 + 1000]]
    f[:6] = [[0, 1, 2], [0, 0, 1], [7, 7, 7], [3, 4, 5], [5, 4, 3], [2, 1, 0]]
    n, a = backend.face_normals(v, f)
    n_ref, a_ref = ref.face_normals(v, f)
    _check_normals(v, f, n, a, n_ref, a_ref)


def test_face_normals_empty(backend):
    n, a = backend.face_normals(np.zeros((0, 3)), np.zeros((0, 3), np.int32))
    assert n.shape == (0, 3) and a.shape == (0,)


def test_edge_angles_open_sheet_with_degenerate_faces(backend):
    rng = np.random.default_rng()
    v, f = _grid_mesh(60, 40, rng, offset=rng.normal(size=3) * 100)
    f = np.concatenate([f, [[0, 0, 1], [5, 5, 5]]])  # zero-area faces
    f = np.concatenate([f, [[0, 1, 2]]])
    e = _edge_faces(f)
    assert len(e) < 3 * len(f) // 2  # boundary edges are not in the list
    n_ref, a_ref = ref.face_normals(v, f)
    angles = backend.edge_angles(n_ref, e)
    angles_ref = ref.edge_angles(n_ref, e)
    assert angles.dtype == np.float64 and angles.shape == angles_ref.shape
    assert np.all(np.abs(angles - angles_ref) <= 1e-5)
    next_to_zero = (a_ref[e[:, 0]] == 0) | (a_ref[e[:, 1]] == 0)
    assert next_to_zero.any() and np.all(angles[next_to_zero] == 0)


def test_edge_angles_random_normals_near_0_and_pi(backend):
    rng = np.random.default_rng()
    n = rng.normal(size=(4000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    tiny = rng.normal(size=(1000, 3)) * 1e-4
    n[1000:2000] = n[:1000] + tiny  # nearly parallel
    n[2000:3000] = -n[:1000] + tiny  # nearly opposite
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[3999] = 0
    e = np.concatenate([np.stack([np.arange(1000), np.arange(1000, 2000)], 1),
                        np.stack([np.arange(1000), np.arange(2000, 3000)], 1),
                        rng.integers(0, 4000, (2000, 2)), [[3999, 5], [5, 3999]]])
    got, want = backend.edge_angles(n, e), ref.edge_angles(n, e)
    assert np.all(np.abs(got - want) <= 1e-5)


def test_edge_angles_empty(backend):
    assert backend.edge_angles(np.zeros((3, 3)), np.zeros((0, 2), np.int32)).shape == (0,)


def test_bad_face_index_is_an_error(device_backend):
    with pytest.raises(IndexError):
        device_backend.face_normals(np.zeros((3, 3)), np.array([[0, 1, 3]]))


@pytest.fixture(scope="module")
def million_face_mesh():
    rng = np.random.default_rng(7)
    v, f = _grid_mesh(709, 709, rng, offset=[250.0, -40.0, 3.0])
    f = np.concatenate([f, [[0, 0, 1], [2, 2, 2]]])
    assert len(f) >= 1_000_000
    return v, f, ref.face_normals(v, f)


def test_face_normals_one_million_faces(device_backend, million_face_mesh):
    v, f, (n_ref, a_ref) = million_face_mesh
    n, a = device_backend.face_normals(v, f)
    _check_normals(v, f, n, a, n_ref, a_ref)
