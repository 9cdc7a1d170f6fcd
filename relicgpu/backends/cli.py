"""`relicgpu backends`: the compute backends available here, their devices and measured speed."""
from __future__ import annotations

import json
import os
import sys


def cli_add_arguments(parser) -> None:
    parser.add_argument("--no-probe", action="store_true",
                        help="list only; skip the timed probe that `auto` uses to choose")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


def _device_name(backend) -> str:
    return getattr(backend, "device_name", None) or "host CPU (float64 reference)"


def cli_main(args) -> int:
    from . import available_backends, fastest_backend, get_backend, probe_times

    names = available_backends()
    rows = []
    times = {} if args.no_probe else probe_times()
    for name in names:
        backend = get_backend(name)
        rows.append({"name": name, "device": _device_name(backend), "probe_s": times.get(name)})
    auto = None if args.no_probe else min(times, key=lambda n: times[n])
    if not args.no_probe:
        fastest_backend.cache_clear()
    env = os.environ.get("RELICGPU_BACKEND") or None
    if args.json:
        json.dump({"backends": rows, "auto": auto, "RELICGPU_BACKEND": env}, sys.stdout, indent=1)
        print()
        return 0
    width = max(len(r["name"]) for r in rows)
    for r in rows:
        t = r["probe_s"]
        shown = "" if t is None else ("   probe: gave up (>5x the best)" if t == float("inf") else f"   probe: {t * 1e3:8.1f} ms")
        print(f"{r['name']:<{width}}  {r['device']}{shown}")
    if auto:
        print(f"auto -> {auto}" + (f"   (RELICGPU_BACKEND={env} overrides it)" if env else ""))
    elif env:
        print(f"RELICGPU_BACKEND={env}")
    return 0
