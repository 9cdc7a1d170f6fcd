"""`relicgpu backends`: the compute backends available here, their devices and measured speed."""
from __future__ import annotations

import json
import os
import sys

from . import (BackendError, BackendRefused, auto_choice, candidate_backends, fastest_backend, get_backend, probe_times,
               selfcheck_results)


def cli_add_arguments(parser) -> None:
    parser.add_argument("--no-probe", action="store_true",
                        help="list only; skip the timed probe that `auto` uses to choose")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


def _device_name(backend) -> str:
    return getattr(backend, "device_name", None) or "host CPU (float64 reference)"


def _status(name: str) -> tuple[str, str, str | None]:
    """(state, device or reason, what the self-check says) of one candidate backend."""
    try:
        backend = get_backend(name)
    except BackendRefused as exc:
        return "refused", str(exc), "refused"
    except BackendError as exc:
        return "unavailable", str(exc), None
    if name == "numpy":
        return "ok", _device_name(backend), "the reference"
    checked = selfcheck_results().get(name, {})
    note = f"ok ({len(checked)} kernel families agree, checked in {getattr(backend, 'selfcheck_s', 0) * 1e3:.0f} ms)"
    refused_widths = getattr(backend, "lcs_masks_refused", None)
    if refused_widths:
        note += f"; LCS vector width {backend.lcs_masks} ({', '.join(map(str, refused_widths))} disagreed)"
    return "ok", _device_name(backend), note


def cli_main(args) -> int:
    rows = []
    for name in candidate_backends():
        state, device, check = _status(name)
        rows.append({"name": name, "state": state, "device": device if state == "ok" else None,
                     "reason": None if state == "ok" else device, "selfcheck": check, "probe_s": None})
    times = {} if args.no_probe else probe_times()
    for r in rows:
        r["probe_s"] = times.get(r["name"])
    auto = None if args.no_probe else auto_choice(times)
    if not args.no_probe:
        fastest_backend.cache_clear()
    env = os.environ.get("RELICGPU_BACKEND") or None
    if args.json:
        json.dump({"backends": rows, "auto": auto, "RELICGPU_BACKEND": env}, sys.stdout, indent=1)
        print()
        return 0
    width = max(len(r["name"]) for r in rows)
    for r in rows:
        if r["state"] != "ok":
            print(f"{r['name']:<{width}}  {r['state'].upper()}: {r['reason']}")
            continue
        t = r["probe_s"]
        shown = "" if t is None else ("   probe: gave up (>5x the best)" if t == float("inf") else f"   probe: {t * 1e3:8.1f} ms")
        print(f"{r['name']:<{width}}  {r['device']}{shown}   self-check: {r['selfcheck']}")
    if auto:
        print(f"auto -> {auto}" + (f"   (RELICGPU_BACKEND={env} overrides it)" if env else ""))
    elif env:
        print(f"RELICGPU_BACKEND={env}")
    return 0
