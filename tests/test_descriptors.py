import numpy as np

from relicgpu.descriptors import descriptor_correspondences, spin_images
from relicgpu.icp import apply


def test_spin_images_are_rigid_invariant_and_flip_for_the_mating_side():
    rng = np.random.default_rng(0)
    xy = rng.random((1500, 2))
    z = 0.05 * np.sin(9 * xy[:, 0]) * np.cos(7 * xy[:, 1])
    pts = np.column_stack([xy, z])
    gx = 0.05 * 9 * np.cos(9 * xy[:, 0]) * np.cos(7 * xy[:, 1])
    gy = -0.05 * 7 * np.sin(9 * xy[:, 0]) * np.sin(7 * xy[:, 1])
    normals = np.column_stack([-gx, -gy, np.ones(len(xy))])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    a = spin_images(pts, normals, 0.15)
    # the mating side: the same surface, moved, with normals pointing the other way
    t = np.eye(4)
    t[:3, :3] = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    t[:3, 3] = [3, 1, -2]
    b = spin_images(apply(t, pts), -normals @ t[:3, :3].T, 0.15, flip=True)
    assert np.allclose(a, b, atol=1e-9)
    assert np.allclose(a.sum(1), 1)
    pairs = descriptor_correspondences(a, b + rng.normal(scale=1e-3, size=b.shape))
    assert len(pairs) > 100
    assert np.mean(pairs[:, 0] == pairs[:, 1]) > 0.5  # most kept matches are the true ones


def test_spin_images_of_nothing():
    assert spin_images(np.zeros((0, 3)), np.zeros((0, 3)), 1.0).shape == (0, 30)
    assert descriptor_correspondences(np.zeros((1, 30)), np.zeros((4, 30))).shape == (0, 2)
