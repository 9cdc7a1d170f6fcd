"""Feature fusion (section 3.8.2, Eq. 29-32): a small MLP maps the features of a
contour point and their relation to its neighbours to one value.

    g(P_i)  = 2 f(P_i) - f(P_{i-1}) - f(P_{i+1})          (Eq. 31)
    g-bar   = [g, 1, 1, 1, 1],  f-bar = [1, 1, 1, 1, f]    (Eq. 30, 32)
    f-hat   = MLP(g-bar * f-bar) = MLP([g, f])             (Eq. 29)

Inference is plain NumPy over arrays (torch is used only to train, in
relicgpu.fusion_train). The weights file (.npz) holds the layers `w0, b0, w1,
b1, ...` (ReLU between layers), the input statistics `mean`, `std` (8 each),
and a JSON `meta` string saying how the weights were made.
"""
from __future__ import annotations

import io as _stdio
import json
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np

from ..io.files import atomic_write_bytes
from ..io.fragment import FragmentError

FEATURE_NAMES = ("kappa", "tau", "chord_right", "chord_left")
INPUT_NAMES = tuple(f"g_{n}" for n in FEATURE_NAMES) + FEATURE_NAMES


@dataclass(frozen=True, eq=False)
class FusionModel:
    weights: tuple[np.ndarray, ...]  # (in, out) matrices
    biases: tuple[np.ndarray, ...]
    mean: np.ndarray  # (8,)
    std: np.ndarray  # (8,)
    meta: dict = field(default_factory=dict)


def fusion_inputs(f: np.ndarray) -> np.ndarray:
    """The 8 numbers [g, f] per point of a closed contour (g-bar * f-bar of Eq. 29-32)."""
    f = np.asarray(f, np.float64).reshape(-1, 4)
    if len(f) == 0:
        return np.zeros((0, 8))
    g = 2 * f - np.roll(f, 1, axis=0) - np.roll(f, -1, axis=0)
    g_bar = np.concatenate([g, np.ones_like(f)], axis=1)
    f_bar = np.concatenate([np.ones_like(f), f], axis=1)
    return g_bar * f_bar


def forward(model: FusionModel, x: np.ndarray) -> np.ndarray:
    """MLP forward pass on standardised inputs: (N,8) -> (N,)."""
    h = (np.asarray(x, np.float64) - model.mean) / model.std
    last = len(model.weights) - 1
    for i, (w, b) in enumerate(zip(model.weights, model.biases)):
        h = h @ w + b
        if i < last:
            h = np.maximum(h, 0.0)
    return h[:, 0]


def fuse(f: np.ndarray, model: FusionModel) -> np.ndarray:
    return forward(model, fusion_inputs(f))


def save_model(path, model: FusionModel) -> None:

    arrays = {"mean": model.mean, "std": model.std, "meta": np.array(json.dumps(model.meta))}
    for i, (w, b) in enumerate(zip(model.weights, model.biases)):
        arrays[f"w{i}"], arrays[f"b{i}"] = w, b
    buf = _stdio.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())


def load_model(path=None) -> FusionModel:
    """Load fusion weights; None gives the weights shipped with relicgpu."""
    if path is None:
        return _shipped()
    return _load(str(path))


@lru_cache(maxsize=8)
def _load(path: str) -> FusionModel:
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise FragmentError(f"{path}: cannot read fusion weights ({exc})") from None
    n = sum(1 for k in data.files if k.startswith("w"))
    try:
        weights = tuple(np.asarray(data[f"w{i}"], np.float64) for i in range(n))
        biases = tuple(np.asarray(data[f"b{i}"], np.float64) for i in range(n))
        mean, std = np.asarray(data["mean"], np.float64), np.asarray(data["std"], np.float64)
    except KeyError as exc:
        raise FragmentError(f"{path}: fusion weights lack the array {exc}") from None
    if n == 0 or weights[0].shape[0] != 8 or weights[-1].shape[1] != 1 or mean.shape != (8,) or std.shape != (8,):
        raise FragmentError(f"{path}: fusion weights must map 8 inputs to 1 output")
    meta = json.loads(str(data["meta"])) if "meta" in data.files else {}
    return FusionModel(weights, biases, mean, np.where(std > 0, std, 1.0), meta)


@lru_cache(maxsize=1)
def _shipped() -> FusionModel:
    ref = resources.files("relicgpu") / "data" / "fusion_default.npz"
    with resources.as_file(ref) as p:
        if Path(p).exists():
            return _load(str(p))
    return hand_weighted_model()


def hand_weighted_model(mix=(0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0), mean=None, std=None) -> FusionModel:
    """An untrained MLP that computes a fixed linear mix of the standardised inputs:
    two ReLU units relu(x.w) and relu(-x.w), output their difference. The default mix
    is curvature alone."""
    w = np.asarray(mix, np.float64).reshape(8, 1)
    w0 = np.concatenate([w, -w], axis=1)
    return FusionModel(
        (w0, np.array([[1.0], [-1.0]])),
        (np.zeros(2), np.zeros(1)),
        np.zeros(8) if mean is None else np.asarray(mean, np.float64),
        np.ones(8) if std is None else np.asarray(std, np.float64),
        {"made_by": "hand_weighted_model", "mix": list(map(float, mix))},
    )
