"""`PairMatch`, what `relicgpu.pair.pipeline.match_pair` finds for two fragments."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, eq=False)
class PairMatch:
    transform: np.ndarray  # 4x4 carrying b onto a
    accepted: bool
    score: float
    rmse: float
    overlap: float
    penetration: float
    correspondences: np.ndarray  # (K,2) point indices into contour_a / contour_b
    contour_a: int
    contour_b: int
    reason: str
    timings: dict = field(default_factory=dict)

    def doc(self) -> dict:
        """The record an assembly caches and reports (no correspondences)."""
        return {"accepted": bool(self.accepted), "transform": np.asarray(self.transform, np.float64).tolist(),
                "score": float(self.score), "rmse": float(self.rmse), "overlap": float(self.overlap),
                "penetration": float(self.penetration), "contour_a": int(self.contour_a),
                "contour_b": int(self.contour_b), "reason": self.reason,
                "timings": {k: float(v) for k, v in self.timings.items()}}

    def to_dict(self) -> dict:
        return {
            "accepted": bool(self.accepted), "transform": self.transform.tolist(), "score": float(self.score),
            "rmse": float(self.rmse), "overlap": float(self.overlap), "penetration": float(self.penetration),
            "contour_a": int(self.contour_a), "contour_b": int(self.contour_b),
            "correspondences": self.correspondences.tolist(), "reason": self.reason,
            "timings": {k: round(float(v), 6) for k, v in self.timings.items()},
        }


def failed_doc(exc: BaseException) -> dict:
    """The record of a match that raised: not accepted, with the error as its reason (not cached)."""
    return {"accepted": False, "transform": np.eye(4).tolist(), "score": 0.0, "rmse": float("inf"),
            "overlap": 0.0, "penetration": 0.0, "reason": f"error: {type(exc).__name__}: {exc}",
            "error": True, "timings": {}}
