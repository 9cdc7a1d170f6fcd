"""Training the feature-fusion MLP (section 3.8.2) with torch: `relicgpu train-fusion -o weights.npz`.

The paper: "by adjusting the weights of the multilayer perceptron, the error rate of
fragment splicing can be reduced". Here the weights are fitted on synthetic breaks
(relicgpu.synth) whose true poses are known:

- data: touching pairs (a, b) of synthetic objects, both prepared at the pair's scale
  s (the mean fragment size); the points of b's contours are moved onto a by the true
  relative pose, and a point of b corresponds to the nearest point of a's contours
  when that lies within 1% of s;
- loss: on corresponding points and on random points more than 3% of s apart, the
  soft flags of Eq. 33 (|V_i - V_j| < Params().lcs_eps made smooth) give a true-flag
  rate TPR and a false-flag rate FPR; the loss -log TPR + 0.5 log FPR pulls fused
  values of corresponding points together and pushes the others apart (see pair_loss);
- model selection by the splicing error itself on held-out pairs: every checkpoint is
  scored by how many held-out pairs get an LCS start near the truth (lcs_check: the LCS
  coarse step of match_pair alone, RANSAC poses over the LCS correspondences, one of them
  within 5% of s of the true pose), ties broken by the share of LCS correspondences that
  are true (within 1% of s); the best few are then judged by pair success of match_pair
  started from the LCS alone (every other start source off).

Only this module imports torch (lazily, inside the functions that train); the training
pairs are made by relicgpu.fusion_data, and they and the scoring helpers here are plain
NumPy and serve scripts/bench_fusion.py too. Inference is relicgpu.pair.fusion (NumPy).
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .backends import resolve
from .errors import CliError
from .fusion_data import TRUE_WITHIN, PairData, _move, build_pairs, contour_inputs, object_specs
from .pair import fusion as fusion_mod
from .pair.icp import ransac_poses
from .pair.lcs import circular_lcs
from .pair.pipeline import match_pair
from .params import Params

NEGATIVE_BEYOND = 0.03  # a negative (non-corresponding) pair lies at least this far apart


# --- scoring (NumPy) ---------------------------------------------------------

@dataclass(frozen=True)
class LcsScore:
    true: int  # LCS correspondences within 1% of the pair scale of the truth
    total: int

    @property
    def share(self) -> float:
        return self.true / self.total if self.total else 0.0


def lcs_score(pair: PairData, model, eps: float) -> LcsScore:
    """Run the circular LCS of match_pair over every contour pair with `model`'s fused values
    and count the correspondences that are true."""
    be = resolve("numpy")
    fa = [fusion_mod.forward(model, x) for x in pair.inputs_a]
    fb = [fusion_mod.forward(model, x) for x in pair.inputs_b]
    true = total = 0
    for ca, A in enumerate(pair.prepared_a.contours):
        for cb in range(len(pair.prepared_b.contours)):
            for m in circular_lcs(fa[ca], fb[cb], eps, be):
                if m.length < 3:
                    continue
                d = np.linalg.norm(A.points[m.pairs[:, 0]] - pair.moved_b[cb][m.pairs[:, 1]], axis=1)
                true += int((d <= TRUE_WITHIN * pair.scale).sum())
                total += len(d)
    return LcsScore(true, total)


START_WITHIN = 0.05  # an LCS start is near the truth when b's vertices lie within this share of the scale (RMS)


def lcs_only(params: Params) -> Params:
    """The parameters with every coarse-start source but the LCS of fused values turned off."""
    off = {k: 0 for k in ("max_patches", "descriptor_radius", "ppf_points") if hasattr(params, k)}
    return params.with_(**off)


def pose_error(pair: PairData, transform: np.ndarray) -> float:
    """RMS distance of b's vertices under `transform` from their true place (object units)."""
    v = pair.prepared_b.fragment.vertices
    return float(np.sqrt(np.mean(np.sum((_move(transform, v) - _move(pair.truth, v)) ** 2, axis=1))))


@dataclass(frozen=True)
class LcsCheck:
    score: LcsScore
    start_ok: bool  # some LCS start lies within START_WITHIN of the truth
    start_error: float  # the nearest LCS start's pose error (inf without starts)


def lcs_check(pair: PairData, model, params: Params | None = None) -> LcsCheck:
    """The LCS coarse step of match_pair alone, with `model`'s fused values: the circular LCS of
    every contour pair, RANSAC poses over its correspondences (same seed, iterations and
    inlier distance as match_pair), and whether one of those starts is near the true pose.
    Cheap (no ICP, no verification): it isolates what the fusion changes."""
    params = params or Params()
    be = resolve("numpy")
    fa = [fusion_mod.forward(model, x) for x in pair.inputs_a]
    fb = [fusion_mod.forward(model, x) for x in pair.inputs_b]
    rng = np.random.default_rng(12345)
    inlier = params.ransac_inlier * pair.scale
    true = total = 0
    best = float("inf")
    for ca, A in enumerate(pair.prepared_a.contours):
        for cb, B in enumerate(pair.prepared_b.contours):
            for m in circular_lcs(fa[ca], fb[cb], params.lcs_eps, be):
                if m.length < 3:
                    continue
                d = np.linalg.norm(A.points[m.pairs[:, 0]] - pair.moved_b[cb][m.pairs[:, 1]], axis=1)
                true += int((d <= TRUE_WITHIN * pair.scale).sum())
                total += len(d)
                src, dst = B.points[m.pairs[:, 1]], A.points[m.pairs[:, 0]]
                for pose, _ in ransac_poses(src, dst, params.ransac_iterations, inlier, rng, keep=2):
                    best = min(best, pose_error(pair, pose))
    return LcsCheck(LcsScore(true, total), best <= START_WITHIN * pair.scale, best)


def with_model(prepared, model, params: Params | None = None):
    """The Prepared fragment with its contours' fused values made by `model` (what
    prepare(fragment, Params(fusion_weights=...)) gives, without segmenting again)."""
    params = params or Params()
    contours = [replace(c, fused=fusion_mod.forward(model, contour_inputs(c, prepared.scale, params)))
                for c in prepared.contours]
    return replace(prepared, contours=contours)


def pair_result(pair: PairData, model, params: Params | None = None) -> tuple[bool, float, object]:
    """match_pair with `model`'s fused values: (correct, pose error, PairMatch). Correct = accepted
    with b's vertices within 1% of the object size (synth objects have unit size) RMS of the truth."""
    params = (params or Params()).with_(second_segmentation=None)  # the model's own contours only
    pa, pb = with_model(pair.prepared_a, model, params), with_model(pair.prepared_b, model, params)
    m = match_pair(pa, pb, params, "numpy", scale=pair.scale)
    err = pose_error(pair, m.transform)
    return bool(m.accepted and err <= 0.01), err, m


# --- training (torch) ------------------------------------------------------

@dataclass(frozen=True)
class TrainConfig:
    train_objects: int = 36
    val_objects: int = 15
    train_seed: int = 0  # synth seeds of the training objects start here
    val_seed: int = 500  # ... and of the validation objects here
    seed: int = 0  # torch initialisation and negative sampling
    hidden: int = 16
    layers: int = 2
    steps: int = 800
    lr: float = 1e-2
    negatives: int = 4  # negatives per positive
    fpr_exponent: float = 0.5  # weight of log(false-flag rate) against -log(true-flag rate)
    temperature: float = 0.25  # of the soft flag, in units of eps
    check_every: int = 50
    finalists: int = 3  # checkpoints judged by pair success
    faces: int = 4000
    pairs_per_object: int = 2


@dataclass
class TrainResult:
    model: fusion_mod.FusionModel
    losses: list
    checkpoints: list  # (step, held-out pairs with an LCS start near the truth, held-out LCS true share)
    meta: dict


def _standardisation(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # median and scaled IQR: the curvature has a heavy tail (kinks), which a plain std lets rule
    mean = np.median(x, axis=0)
    q1, q3 = np.percentile(x, [25, 75], axis=0)
    std = (q3 - q1) / 1.349
    return mean, np.where(std > 1e-12, std, 1.0)


def _torch_net(hidden: int, layers: int):
    import torch

    mods, width = [], 8
    for _ in range(layers):
        mods += [torch.nn.Linear(width, hidden), torch.nn.ReLU()]
        width = hidden
    mods.append(torch.nn.Linear(width, 1))
    return torch.nn.Sequential(*mods).double()


def to_model(net, mean, std, meta=None) -> fusion_mod.FusionModel:
    """The NumPy FusionModel of a torch Sequential of Linear/ReLU layers."""
    import torch

    lin = [m for m in net if isinstance(m, torch.nn.Linear)]
    ws = tuple(m.weight.detach().cpu().double().numpy().T.copy() for m in lin)
    bs = tuple(m.bias.detach().cpu().double().numpy().copy() for m in lin)
    return fusion_mod.FusionModel(ws, bs, np.asarray(mean, np.float64), np.asarray(std, np.float64), dict(meta or {}))


def torch_forward(net, mean, std, x: np.ndarray) -> np.ndarray:
    import torch

    with torch.no_grad():
        h = (torch.as_tensor(np.asarray(x, np.float64)) - torch.as_tensor(mean)) / torch.as_tensor(std)
        return net(h)[:, 0].numpy()


def _training_arrays(pairs: list[PairData]):
    """All contour points of all pairs in one array, the positive index pairs into it, and per
    pair the index ranges and moved positions for sampling negatives."""
    xs, pos, groups = [], [], []
    n = 0
    for p in pairs:
        off_a, off_b = [], []
        for x in p.inputs_a:
            off_a.append(n)
            xs.append(x)
            n += len(x)
        for x in p.inputs_b:
            off_b.append(n)
            xs.append(x)
            n += len(x)
        if len(p.corr):
            ia = np.asarray(off_a)[p.corr[:, 0]] + p.corr[:, 1]
            ib = np.asarray(off_b)[p.corr[:, 2]] + p.corr[:, 3]
            pos.append(np.stack([ia, ib], 1))
        if p.inputs_a and p.inputs_b:
            idx_a = np.concatenate([o + np.arange(len(x)) for o, x in zip(off_a, p.inputs_a)])
            idx_b = np.concatenate([o + np.arange(len(x)) for o, x in zip(off_b, p.inputs_b)])
            pts_a = np.concatenate([c.points for c in p.prepared_a.contours])
            pts_b = np.concatenate(p.moved_b)
            groups.append((idx_a, idx_b, pts_a, pts_b, NEGATIVE_BEYOND * p.scale, len(p.corr)))
    x = np.concatenate(xs) if xs else np.zeros((0, 8))
    return x, (np.concatenate(pos) if pos else np.zeros((0, 2), np.int64)), groups


def _negatives(groups, count_per_group: list[int], rng: np.random.Generator) -> np.ndarray:
    out = []
    for (idx_a, idx_b, pts_a, pts_b, beyond, _), k in zip(groups, count_per_group):
        if k <= 0:
            continue
        ka = rng.integers(0, len(idx_a), 2 * k)
        kb = rng.integers(0, len(idx_b), 2 * k)
        far = np.linalg.norm(pts_a[ka] - pts_b[kb], axis=1) > beyond
        out.append(np.stack([idx_a[ka[far][:k]], idx_b[kb[far][:k]]], 1))
    return np.concatenate(out) if out else np.zeros((0, 2), np.int64)


def pair_loss(out, pos, neg, eps: float, cfg: TrainConfig):
    """-log(soft true-flag rate) + fpr_exponent * log(soft false-flag rate).

    A soft flag is sigmoid((1 - |V_i - V_j| / eps) / temperature), Eq. 33's flag made smooth.
    The LCS of unrelated sequences grows about like the square root of their flag density,
    the run along the true alignment like the share of true pairs flagged: the ratio
    TPR / FPR^0.5 is what makes the true alignment the longest.
    """
    import torch

    t = cfg.temperature
    tpr = torch.sigmoid((1 - (out[pos[:, 0]] - out[pos[:, 1]]).abs() / eps) / t).mean()
    fpr = torch.sigmoid((1 - (out[neg[:, 0]] - out[neg[:, 1]]).abs() / eps) / t).mean()
    return -torch.log(tpr) + cfg.fpr_exponent * torch.log(fpr)


def fit(pairs: list[PairData], cfg: TrainConfig, eps: float, steps: int | None = None, on_check=None,
        progress: bool = True):
    """Fit an MLP on the pairs; returns (net, mean, std, losses). `on_check(step, net)` runs
    every cfg.check_every steps and at the end."""
    import torch
    from tqdm import tqdm

    torch.manual_seed(cfg.seed)
    torch.use_deterministic_algorithms(True)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a tiny net: threads only add overhead and run-to-run noise
    rng = np.random.default_rng(cfg.seed)
    x, pos, groups = _training_arrays(pairs)
    if len(pos) == 0:
        raise ValueError("no true correspondences in the training pairs")
    mean, std = _standardisation(x)
    xt = torch.as_tensor((x - mean) / std)
    post = torch.as_tensor(pos)
    per_group = [g[5] * cfg.negatives for g in groups]
    net = _torch_net(cfg.hidden, cfg.layers)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    steps = cfg.steps if steps is None else steps
    losses = []
    for step in tqdm(range(1, steps + 1), desc="train-fusion", disable=not progress, file=sys.stderr):
        neg = torch.as_tensor(_negatives(groups, per_group, rng))
        out = net(xt)[:, 0]
        loss = pair_loss(out, post, neg, eps, cfg)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
        if on_check is not None and (step % cfg.check_every == 0 or step == steps):
            on_check(step, net, mean, std)
    torch.set_num_threads(threads)
    return net, mean, std, losses


def train(cfg: TrainConfig | None = None, params: Params | None = None, progress: bool = True, cache_dir=None,
          log=None) -> TrainResult:
    """Build the data, fit, select the checkpoint by the splicing error on held-out pairs."""
    import copy

    cfg = cfg or TrainConfig()
    params = params or Params()
    log = log or (lambda *a: None)
    eps = params.lcs_eps
    t0 = time.perf_counter()
    train_pairs = build_pairs(object_specs(cfg.train_objects, cfg.train_seed), params, cfg.faces,
                              cfg.pairs_per_object, progress, cache_dir, "training pairs")
    # held-out objects of 3 pieces first: more pairs, each with fracture on several sides
    val_pairs = build_pairs(object_specs(cfg.val_objects, cfg.val_seed, pieces=(3, 4, 2)), params, cfg.faces,
                            cfg.pairs_per_object, progress, cache_dir, "held-out pairs")
    t_data = time.perf_counter() - t0
    log(f"{len(train_pairs)} training pairs ({sum(len(p.corr) for p in train_pairs)} true correspondences), "
        f"{len(val_pairs)} held-out pairs, in {t_data:.0f} s")

    checkpoints = []

    def check(step, net, mean, std):
        model = to_model(net, mean, std)
        checks = [lcs_check(p, model, params) for p in val_pairs]
        starts = sum(c.start_ok for c in checks)
        share = sum(c.score.true for c in checks) / max(1, sum(c.score.total for c in checks))
        checkpoints.append((step, starts, share, copy.deepcopy(net), mean, std))
        log(f"  step {step}: held-out pairs with an LCS start near the truth {starts}/{len(val_pairs)}, "
            f"LCS true share {share:.4f}")

    t1 = time.perf_counter()
    net, mean, std, losses = fit(train_pairs, cfg, eps, on_check=check, progress=progress)
    t_fit = time.perf_counter() - t1

    # the checkpoints with the most held-out LCS starts near the truth (then the higher LCS true
    # share), judged at last by the splicing itself: match_pair from the LCS starts alone
    t2 = time.perf_counter()
    only = lcs_only(params)
    finalists = sorted(checkpoints, key=lambda c: (-c[1], -c[2], c[0]))[: cfg.finalists]
    judged = []
    for step, starts, share, net_k, mean_k, std_k in finalists:
        model = to_model(net_k, mean_k, std_k)
        results = [pair_result(p, model, only) for p in val_pairs]
        wins = sum(r[0] for r in results)
        median_error = float(np.median([r[1] for r in results]))
        judged.append((wins, starts, share, -step, step, median_error, net_k, mean_k, std_k))
        log(f"  step {step}: LCS-only pair success {wins}/{len(val_pairs)}, median pose error {median_error:.3g}")
    wins, starts, share, _, step, median_error, net_k, mean_k, std_k = max(judged, key=lambda j: j[:4])
    t_select = time.perf_counter() - t2
    meta = {
        "made_by": "relicgpu.fusion_train.train", "config": cfg.__dict__, "lcs_eps": eps,
        "feature_stride": params.feature_stride,
        "selected_step": step, "heldout_pairs": len(val_pairs), "heldout_lcs_true_share": round(share, 4),
        "heldout_lcs_starts_near_truth": starts, "heldout_lcs_only_pair_success": wins,
        "heldout_lcs_only_median_pose_error": round(median_error, 4), "training_pairs": len(train_pairs),
        "true_correspondences": int(sum(len(p.corr) for p in train_pairs)),
        "seconds": {"data": round(t_data, 1), "fit": round(t_fit, 1), "select": round(t_select, 1)},
        "checkpoints": [[c[0], c[1], round(c[2], 4)] for c in checkpoints],
    }
    model = to_model(net_k, mean_k, std_k, meta)
    return TrainResult(model, losses, [(c[0], c[1], c[2]) for c in checkpoints], meta)


# --- CLI -------------------------------------------------------------------

def cli_add_arguments(parser) -> None:
    d = TrainConfig()
    parser.add_argument("-o", "--out", required=True, help="weights file to write (.npz)")
    parser.add_argument("--seed", type=int, default=d.seed, help="torch initialisation and sampling seed")
    parser.add_argument("--train-objects", type=int, default=d.train_objects, help="synthetic objects to train on")
    parser.add_argument("--val-objects", type=int, default=d.val_objects, help="held-out objects for model selection")
    parser.add_argument("--steps", type=int, default=d.steps, help="optimiser steps (full batch)")
    parser.add_argument("--hidden", type=int, default=d.hidden, help="units per hidden layer")
    parser.add_argument("--fpr-exponent", type=float, default=d.fpr_exponent,
                        help="weight of log(false-flag rate) in the loss (higher: sparser LCS flags)")
    parser.add_argument("--cache-dir", default=None, help="where prepared training pairs are cached (default: temp dir)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar or log on stderr")


def cli_main(args) -> int:
    out = Path(args.out)
    if out.suffix != ".npz":
        raise CliError(f"{out}: the weights file must end in .npz")
    if args.train_objects < 1 or args.val_objects < 1 or args.steps < 1 or args.hidden < 1 or args.fpr_exponent <= 0:
        raise CliError("--train-objects, --val-objects, --steps, --hidden and --fpr-exponent must be positive")
    cfg = replace(TrainConfig(), seed=args.seed, train_objects=args.train_objects, val_objects=args.val_objects,
                  steps=args.steps, hidden=args.hidden, fpr_exponent=args.fpr_exponent)
    try:
        import torch  # noqa: F401
    except ImportError:
        raise CliError("training needs torch: pip install 'relicgpu[train]'") from None
    log = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr))
    t0 = time.perf_counter()
    result = train(cfg, progress=not args.quiet, cache_dir=args.cache_dir, log=log)
    fusion_mod.save_model(out, result.model)
    m = result.meta
    log(f"wrote {out}: step {m['selected_step']}, held-out LCS true share {m['heldout_lcs_true_share']:.3f}, "
        f"LCS-only pair success {m['heldout_lcs_only_pair_success']}/{m['heldout_pairs']} "
        f"({time.perf_counter() - t0:.0f} s)")
    return 0
