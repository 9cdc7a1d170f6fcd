"""The supervised fragment classifier (`relicgpu train-classifier`, `relicgpu group
--classifier`): a small PointNet over surface points joined with the descriptors, trained with
torch."""
from __future__ import annotations

import csv
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .describe import _grouping_params, describe_all, descriptor_matrix

from ..backends import resolve
from ..io.files import atomic_write_bytes
from ..io.fragment import Fragment, FragmentError
from ..pair.segment import segment

CLASSIFIER_POINTS = 256


# --- supervised: a small PointNet ------------------------------------------------

def point_features(fragment: Fragment, ref_length: float, n_points: int = CLASSIFIER_POINTS,
                   rng: np.random.Generator | None = None, params=None, copies: int = 1) -> np.ndarray:
    """(copies, n_points, 7) area-weighted surface samples: position in the fragment's principal
    frame (over ref_length), face normal in that frame, fracture flag; independent samples."""
    rng = rng or np.random.default_rng(0)
    v, f = np.asarray(fragment.vertices, np.float64), np.asarray(fragment.faces, np.int64)
    seg = segment(v, f, _grouping_params(params), fragment.size, resolve("numpy"))
    return np.stack([_sample_points(v, f, seg, ref_length, n_points, rng) for _ in range(copies)])


def _sample_points(v, f, seg, ref_length, n_points, rng):
    p = seg.areas / seg.areas.sum()
    idx = rng.choice(len(f), n_points, p=p)
    r1, r2 = rng.random((2, n_points))
    s = np.sqrt(r1)
    tri = v[f[idx]]
    pts = (1 - s)[:, None] * tri[:, 0] + (s * (1 - r2))[:, None] * tri[:, 1] + (s * r2)[:, None] * tri[:, 2]
    centre = (v[f].mean(1) * seg.areas[:, None]).sum(0) / seg.areas.sum()
    _, vec = np.linalg.eigh(np.cov((pts - centre).T))
    frame = vec[:, ::-1]
    local = (pts - centre) @ frame
    # the sign of each axis: the side holding the third moment's weight (skewness > 0)
    signs = np.sign(np.sum(local ** 3, axis=0))
    signs[signs == 0] = 1
    signs[2] = signs[0] * signs[1] * np.linalg.det(frame)  # keep a rotation
    frame = frame * signs
    local = (pts - centre) @ frame
    normals = seg.normals[idx] @ frame
    return np.hstack([local / ref_length, normals, seg.fracture_faces[idx, None].astype(np.float64)])


def _net(n_desc: int, n_classes: int):
    import torch.nn as nn

    class PointNetClassifier(nn.Module):
        def __init__(self):
            super().__init__()
            self.point = nn.Sequential(nn.Conv1d(7, 32, 1), nn.BatchNorm1d(32), nn.ReLU(),
                                       nn.Conv1d(32, 64, 1), nn.BatchNorm1d(64), nn.ReLU(),
                                       nn.Conv1d(64, 128, 1), nn.BatchNorm1d(128), nn.ReLU())
            self.head = nn.Sequential(nn.Linear(128 + n_desc, 64), nn.BatchNorm1d(64), nn.ReLU(),
                                      nn.Dropout(0.2), nn.Linear(64, n_classes))

        def forward(self, pts, desc):
            import torch
            g = self.point(pts.transpose(1, 2)).max(dim=2).values
            return self.head(torch.cat([g, desc], dim=1))

    return PointNetClassifier()


@dataclass
class Classifier:
    classes: list[str]
    ref_length: float
    desc_mean: np.ndarray
    desc_std: np.ndarray
    state: dict  # torch state dict
    history: list = field(default_factory=list)  # mean training loss per epoch
    timings: dict = field(default_factory=dict)

    def save(self, path) -> None:
        import io as _io
        import torch
        buf = _io.BytesIO()
        torch.save({"version": 1, "classes": self.classes, "ref_length": self.ref_length,
                    "desc_mean": self.desc_mean.tolist(), "desc_std": self.desc_std.tolist(),
                    "state": self.state}, buf)
        atomic_write_bytes(path, buf.getvalue())

    @staticmethod
    def load(path) -> "Classifier":
        import torch
        try:
            d = torch.load(path, map_location="cpu", weights_only=True)
            return Classifier(list(d["classes"]), float(d["ref_length"]), np.asarray(d["desc_mean"]),
                              np.asarray(d["desc_std"]), d["state"])
        except FileNotFoundError:
            raise FragmentError(f"{path}: no such file") from None
        except Exception as exc:
            raise FragmentError(f"{path}: not a relicgpu classifier ({exc})") from None

    def predict(self, fragments: list[Fragment], params=None) -> tuple[list[str], np.ndarray]:
        """Class name per fragment and the class probabilities (n, C)."""
        import torch
        desc = describe_all(fragments, params)
        x = np.stack([d.vector(self.ref_length) for d in desc])
        if x.shape[1] != len(self.desc_mean):
            raise FragmentError(f"the classifier was trained with {len(self.desc_mean)} descriptors, these "
                                f"fragments give {x.shape[1]} (colour present in one and not the other?)")
        pts = np.stack([point_features(fr, self.ref_length, params=params)[0] for fr in fragments])
        net = _net(x.shape[1], len(self.classes))
        net.load_state_dict(self.state)
        net.eval()
        with torch.no_grad():
            logits = net(torch.as_tensor(pts, dtype=torch.float32),
                         torch.as_tensor((x - self.desc_mean) / self.desc_std, dtype=torch.float32))
            prob = torch.softmax(logits, 1).numpy()
        return [self.classes[k] for k in prob.argmax(1)], prob


def train_classifier(fragments: list[Fragment], labels: list[str], epochs: int = 120, seed: int = 0,
                     params=None, progress: bool = False, copies: int = 4) -> Classifier:
    """Train the PointNet classifier on labelled fragments (torch, CPU or CUDA)."""
    import torch

    if len(fragments) != len(labels) or not fragments:
        raise FragmentError("need one label per fragment and at least one fragment")
    classes = sorted(set(labels))
    if len(classes) < 2:
        raise FragmentError(f"need at least two classes to train, got {classes}")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a net this small runs fastest on one thread, above all on a shared CPU
    try:
        return _train(fragments, labels, classes, epochs, seed, params, progress, copies)
    finally:
        torch.set_num_threads(threads)


def _train(fragments, labels, classes, epochs, seed, params, progress, copies) -> Classifier:
    import torch

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    desc = describe_all(fragments, params, progress)
    x, L = descriptor_matrix(desc)
    mean, std = x.mean(0), np.maximum(x.std(0), 1e-6)
    xs = (x - mean) / std
    y = np.array([classes.index(l) for l in labels])
    # a few independent point samples per fragment: the sampling itself is an augmentation
    pts = np.stack([point_features(fr, L, rng=rng, params=params, copies=copies)
                    for fr in fragments])  # (n, copies, P, 7)
    timings = {"features": time.perf_counter() - t0}
    t0 = time.perf_counter()
    net = _net(x.shape[1], len(classes))
    opt = torch.optim.AdamW(net.parameters(), lr=2e-3, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
    pts_t = torch.as_tensor(pts, dtype=torch.float32)
    xs_t = torch.as_tensor(xs, dtype=torch.float32)
    y_t = torch.as_tensor(y)
    n = len(fragments)
    batch = min(32, n)
    history = []
    bar = range(epochs)
    if progress:
        from tqdm import tqdm
        bar = tqdm(bar, desc="train", unit="epoch", file=sys.stderr, leave=False)
    for _ in bar:
        net.train()
        order = torch.randperm(n)
        total = 0.0
        for s in range(0, n - (n % batch if n > batch and n % batch == 1 else 0), batch):
            b = order[s:s + batch]
            if len(b) < 2:
                continue
            c = torch.randint(0, copies, (len(b),))
            p = pts_t[b, c].clone()
            # mirror-free augmentation: flip two principal axes together, jitter, scale +-5%
            flip = torch.where(torch.rand(len(b), 1, 2) < 0.5, -1.0, 1.0)
            p[:, :, [0, 1]] *= flip
            p[:, :, [3, 4]] *= flip
            p[:, :, :3] = p[:, :, :3] * (1 + 0.05 * (2 * torch.rand(len(b), 1, 1) - 1))
            p[:, :, :3] += 0.002 * torch.randn_like(p[:, :, :3])
            d = xs_t[b] + 0.05 * torch.randn_like(xs_t[b])
            loss = torch.nn.functional.cross_entropy(net(p, d), y_t[b], label_smoothing=0.05)
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(b)
        sched.step()
        history.append(total / n)
    state = {k: v.detach().cpu() for k, v in net.state_dict().items()}
    timings["train"] = time.perf_counter() - t0
    return Classifier(classes, L, mean, std, state, history, timings)


def read_labels_csv(path) -> tuple[list[Path], list[str]]:
    """LABELS.csv: rows `file,label` (a header row `file,label` is skipped); files relative to the csv."""
    p = Path(path)
    try:
        rows = list(csv.reader(p.read_text().splitlines()))
    except FileNotFoundError:
        raise FragmentError(f"{p}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise FragmentError(f"{p}: unreadable ({exc})") from None
    files, labels = [], []
    for line, row in enumerate(rows, 1):
        if not row or not "".join(row).strip() or row[0].startswith("#"):
            continue
        if line == 1 and [c.strip().lower() for c in row[:2]] == ["file", "label"]:
            continue
        if len(row) != 2 or not row[0].strip() or not row[1].strip():
            raise FragmentError(f"{p}: line {line}: expected `file,label`, got {','.join(row)!r}")
        f = Path(row[0].strip())
        files.append(f if f.is_absolute() else p.parent / f)
        labels.append(row[1].strip())
    if not files:
        raise FragmentError(f"{p}: no labelled files")
    return files, labels
