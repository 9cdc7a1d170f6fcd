"""Fusion training (torch): NumPy and torch forward passes agree, training lowers the loss,
the true correspondences of a synthetic pair are right, the shipped weights load."""
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from relicgpu import fusion_data as fd  # noqa: E402
from relicgpu.pair import fusion as fusion_mod  # noqa: E402
from relicgpu import fusion_train as ft  # noqa: E402
from relicgpu.params import Params  # noqa: E402


@pytest.fixture(scope="module")
def tiny_pairs(tmp_path_factory):
    specs = [fd.ObjectSpec("slab", 2, 3, 0.0), fd.ObjectSpec("vase", 2, 4, 0.0005)]
    return fd.build_pairs(specs, faces=1500, progress=False, cache_dir=tmp_path_factory.mktemp("cache"))


def test_numpy_forward_equals_torch_forward():
    torch.manual_seed(0)
    net = ft._torch_net(16, 2)
    rng = np.random.default_rng(1)
    x = rng.normal(size=(500, 8)) * 3
    mean, std = rng.normal(size=8), rng.random(8) + 0.5
    model = ft.to_model(net, mean, std)
    assert np.max(np.abs(fusion_mod.forward(model, x) - ft.torch_forward(net, mean, std, x))) < 1e-6


def test_true_correspondences_are_near_in_the_object_frame(tiny_pairs):
    for p in tiny_pairs:
        assert len(p.corr) > 20
        pa = np.concatenate([c.points for c in p.prepared_a.contours])
        ca, ia, cb, ib = p.corr.T
        a_pts = np.array([p.prepared_a.contours[c].points[i] for c, i in zip(ca, ia)])
        b_pts = np.array([p.moved_b[c][i] for c, i in zip(cb, ib)])
        assert np.all(np.linalg.norm(a_pts - b_pts, axis=1) <= fd.TRUE_WITHIN * p.scale + 1e-12)
        # and b's contour points are truly moved: most lie near a's contours
        assert len(p.corr) > 0.3 * min(len(pa), sum(len(m) for m in p.moved_b))


def test_training_on_a_tiny_set_lowers_the_loss_and_is_deterministic(tiny_pairs):
    cfg = ft.TrainConfig(steps=40, check_every=1000, seed=3)
    net, mean, std, losses = ft.fit(tiny_pairs, cfg, Params().lcs_eps, progress=False)
    assert np.mean(losses[-5:]) < losses[0] - 0.05
    net2, _, _, losses2 = ft.fit(tiny_pairs, cfg, Params().lcs_eps, progress=False)
    assert losses == losses2
    x = np.concatenate(tiny_pairs[0].inputs_a)
    assert np.array_equal(ft.torch_forward(net, mean, std, x), ft.torch_forward(net2, mean, std, x))


def test_lcs_score_counts_true_correspondences(tiny_pairs):
    s = ft.lcs_score(tiny_pairs[0], fusion_mod.hand_weighted_model(), Params().lcs_eps)
    assert 0 <= s.true <= s.total and s.total > 0
    assert 0.0 <= s.share <= 1.0


def test_lcs_check_is_the_lcs_step_of_match_pair(tiny_pairs):
    pair, model = tiny_pairs[0], fusion_mod.hand_weighted_model()
    check = ft.lcs_check(pair, model)
    assert check.score == ft.lcs_score(pair, model, Params().lcs_eps)
    assert check.start_ok == (check.start_error <= ft.START_WITHIN * pair.scale)
    assert np.isfinite(check.start_error)
    # the true pose itself has error 0, a pose 10% of the scale off has error 0.1 * scale
    assert ft.pose_error(pair, pair.truth) < 1e-12
    shifted = pair.truth.copy()
    shifted[:3, 3] += [0.1 * pair.scale, 0, 0]
    assert np.isclose(ft.pose_error(pair, shifted), 0.1 * pair.scale)
    # a constant fusion flags every point pair, so its LCS is as long as can be
    const = fusion_mod.hand_weighted_model(np.zeros(8))
    assert ft.lcs_check(pair, const).score.total >= check.score.total


def test_lcs_only_turns_the_other_start_sources_off():
    p = ft.lcs_only(Params())
    for name in ("max_patches", "descriptor_radius", "ppf_points"):
        if hasattr(p, name):
            assert getattr(p, name) == 0


def test_shipped_weights_are_a_trained_mlp_with_their_record():
    model = fusion_mod.load_model(None)
    assert model.meta.get("made_by") == "relicgpu.fusion_train.train"
    assert model.meta.get("feature_stride") == Params().feature_stride  # trained on the features prepare makes
    assert model.weights[0].shape[0] == 8 and model.weights[-1].shape[1] == 1
    out = fusion_mod.fuse(np.random.default_rng(0).normal(size=(50, 4)), model)
    assert out.shape == (50,) and np.all(np.isfinite(out))
    # the record beside the weights describes these very weights and the command that made them
    data = Path(fusion_mod.__file__).parents[1] / "data"
    record = json.loads((data / "fusion_default.json").read_text())
    assert record["sha256"] == hashlib.sha256((data / "fusion_default.npz").read_bytes()).hexdigest()
    assert record["command"].startswith("relicgpu train-fusion ") and f"--seed {record['seed']}" in record["command"]
    assert record["seed"] == model.meta["config"]["seed"]
    assert record["heldout"]["selected_step"] == model.meta["selected_step"]


def test_cli_rejects_a_weights_path_without_npz(tmp_path, capsys):
    from relicgpu.cli import main

    assert main(["train-fusion", "-o", str(tmp_path / "w.bin"), "--quiet"]) == 2
    assert "npz" in capsys.readouterr().err
