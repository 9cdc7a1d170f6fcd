"""relicgpu.synth.thin: bookshelves and a plant cut in two, with their truth."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from relicgpu.synth import thin


@pytest.mark.parametrize("family", ["shelf02-flat", "shelf04-smooth", "plant-rough"])
def test_a_thin_object_is_cut_into_two_touching_halves(family):
    r = thin.generate(family, seed=3)
    assert len(r.fragments) == 2 and r.touching == [(0, 1)]
    placed = r.placed_back()
    for i, (f, labels) in enumerate(zip(placed, r.fracture_faces)):
        assert len(trimesh.Trimesh(f.vertices, f.faces).split(only_watertight=False)) == 1
        assert 0 < labels.mean() < 1
        other = trimesh.Trimesh(placed[1 - i].vertices, placed[1 - i].faces)
        centres = f.vertices[f.faces].mean(1)
        _, cut, _ = trimesh.proximity.closest_point(other, centres[labels][:200])
        _, skin, _ = trimesh.proximity.closest_point(other, centres[~labels][:200])
        assert np.median(cut) < 1e-6 < np.median(skin)  # the cut lies on the partner, the skin does not
    assert np.abs(r.fragments[0].vertices - placed[0].vertices).max() > 0.1  # scattered
    again = thin.generate(family, seed=3)
    np.testing.assert_array_equal(again.fragments[1].vertices, r.fragments[1].vertices)


def test_a_board_is_as_thick_as_asked():
    for t in (0.02, 0.04):
        assert thin.bookshelf(t).volume() == pytest.approx(t * (2 * 0.3 * 1.0 + 5 * 0.8 * 0.3 + 0.8 * 1.0), rel=0.15)


def test_unknown_thin_family_is_refused():
    with pytest.raises(ValueError, match="unknown thin family"):
        thin.generate("shelf04-jagged")
