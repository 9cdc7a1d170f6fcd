"""The pipeline stages behind the viewer: relicgpu.prepare, match_pair and assemble,
imported on first use (tests and embedders pass their own to create_app)."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import relicgpu

from .serialize import timings_to_json


def default_prepare(fragment, scale):
    """relicgpu.prepare(fragment, scale=scale)."""
    return relicgpu.prepare(fragment, scale=scale)


def default_match_pair(prepared_a, prepared_b, heads, scale):
    """relicgpu.match_pair of two prepared fragments, at their own scale."""
    # The same scale as the prepared fragments: match_pair then reuses them rather than preparing
    # again at the pair's own scale, so head indices picked on the shown contours mean the same points.
    return relicgpu.match_pair(prepared_a, prepared_b, heads=heads, scale=scale)


def run_assembly(fragments_dir: Path, out_dir: Path, report, progress=None) -> dict:
    """Assemble a case's fragments with relicgpu.assemble, writing its outputs to out_dir.

    Parameters
    ----------
    fragments_dir : Path
        The case's fragments/ folder.
    out_dir : Path
        Where assembly.json, assembly.glb and merged.stl go.
    report : callable
        report(stage=..., message=...) for the job's state.
    progress : callable or bool, optional
        Passed on to relicgpu.assemble (default: a callback feeding report; the
        terminal's tqdm bars when True).

    Returns
    -------
    dict
        fragments, placed, groups, accepted, used (those assemble reported) and timings.
    """

    report(stage="assembling", message=f"assembling {fragments_dir.parent.name}")
    result = relicgpu.assemble(fragments_dir, out_dir=out_dir,
                               progress=progress_callback(report) if progress is None else progress)
    stats = getattr(result, "stats", {}) or {}
    return {k: stats[k] for k in ("fragments", "placed", "groups", "accepted", "used") if k in stats} | {
        "timings": timings_to_json(getattr(result, "timings", None))}


def progress_callback(report):
    """A `progress` argument for relicgpu.assemble, for when it calls progress(stage, done, total).

    (A plain truthy value to an assemble that only draws tqdm bars on a terminal.)

    Parameters
    ----------
    report : callable
        Called as report(stage=, done=, total=, message=) on each progress call.

    Returns
    -------
    callable
        progress(*args, **kwargs).
    """
    def progress(*args, **kwargs):
        stage = kwargs.get("stage", args[0] if args and isinstance(args[0], str) else None)
        nums = [a for a in args if isinstance(a, (int, float)) and not isinstance(a, bool)]
        done = kwargs.get("done", nums[0] if len(nums) >= 1 else None)
        total = kwargs.get("total", nums[1] if len(nums) >= 2 else None)
        report(stage=stage, done=done, total=total, message=kwargs.get("message"))
    return progress


def pipeline_available(module: str) -> bool:
    """Whether a module (e.g. "relicgpu.pair.pipeline") can be imported, without importing it."""
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False
