"""PoCL's CPU target, repaired where PoCL cannot find one itself (see `repair_pocl_cpu_name`).

`relicgpu.backends.opencl` calls `repair_pocl_cpu_name()` before pyopencl first lists
platforms or devices; it acts once per process.
"""
from __future__ import annotations

import ctypes
import importlib.util
import mmap
import os
import platform as _platform
import struct
import sys
import threading
from pathlib import Path

_pocl_cpu_name_buffer = None  # keeps the patched CPU name alive
_repair_lock = threading.Lock()
_repaired: list = []  # [the name written or None], once the repair has run


def repair_pocl_cpu_name() -> str | None:
    """Run `_repair_pocl_cpu_name` once per process; returns what it returned (the CPU
    name written into PoCL, or None when nothing was done)."""
    with _repair_lock:
        if not _repaired:
            _repaired.append(_repair_pocl_cpu_name())
        return _repaired[0]


def _host_llvm_cpu() -> str:
    """An LLVM CPU name that the host can run, from /proc/cpuinfo flags."""
    flags: set[str] = set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                flags = set(line.split(":", 1)[1].split())
                break
    except OSError:
        pass
    if {"avx512f", "avx512bw", "avx512vl", "avx512dq", "avx512cd"} <= flags:
        return "skylake-avx512"
    if {"avx2", "fma", "bmi2"} <= flags:
        return "haswell"
    if "sse4_2" in flags:
        return "nehalem"
    return "x86-64"


def _repair_pocl_cpu_name() -> str | None:
    """Give PoCL a CPU target it can compile for, where it cannot find one itself.

    The PoCL on PyPI (pocl-binary-distribution 3.0, PoCL 3.0-rc2 with LLVM 14, the
    newest there) asks LLVM for the host CPU name; on CPUs newer than LLVM 14 (AMD
    Zen 5) LLVM answers "generic", which clang then rejects ("unknown target CPU
    'generic'", pocl issue #1049), so every program build fails. PoCL 3.0 reads no
    setting for its CPU target (no environment variable, and build options do not
    reach its code generator), and the wheel links LLVM statically with -Bsymbolic,
    so the name cannot be interposed either. What is left, and what this does: the
    exported `pocl_get_llvm_cpu_name` is overwritten in memory with a jump to
    strdup(<a name LLVM knows>), chosen from the CPU's feature flags. Whatever it
    compiles is then self-checked against the NumPy reference like any backend.

    Runs when PoCL reports "generic", or always with RELICGPU_POCL_CPU=<LLVM CPU name>
    (to choose PoCL's target by hand, e.g. `haswell`); only on x86-64 Linux, and
    before pyopencl first lists devices. RELICGPU_POCL_NO_REPAIR=1 skips it.
    Returns the name written, or None when nothing was done."""
    global _pocl_cpu_name_buffer
    if _pocl_cpu_name_buffer is not None or os.environ.get("RELICGPU_POCL_NO_REPAIR"):
        return None
    if _platform.system() != "Linux" or _platform.machine() != "x86_64":
        return None
    wanted = os.environ.get("RELICGPU_POCL_CPU") or None
    spec = importlib.util.find_spec("pyopencl")
    if spec is None or not spec.submodule_search_locations:
        return None
    libdir = Path(list(spec.submodule_search_locations)[0]) / ".libs"
    candidates = sorted(libdir.glob("libpocl*.so*")) if libdir.is_dir() else []
    try:
        lib = ctypes.CDLL(str(candidates[0]), mode=ctypes.RTLD_GLOBAL)
        func = lib.pocl_get_llvm_cpu_name
    except (IndexError, OSError, AttributeError):
        if wanted:
            print(f"relicgpu: warning: RELICGPU_POCL_CPU={wanted} ignored: pyopencl here does not carry the "
                  "PoCL of pocl-binary-distribution", file=sys.stderr)
        return None
    func.restype = ctypes.c_void_p
    libc = ctypes.CDLL(None)
    libc.free.argtypes = [ctypes.c_void_p]
    ptr = func()
    current = ctypes.string_at(ptr).decode() if ptr else ""
    libc.free(ptr)
    if current != "generic" and wanted is None:
        return None
    name = wanted or _host_llvm_cpu()
    _pocl_cpu_name_buffer = ctypes.create_string_buffer(name.encode())
    strdup = ctypes.cast(libc.strdup, ctypes.c_void_p).value
    addr = ctypes.cast(func, ctypes.c_void_p).value
    # mov rdi, <name>; mov rax, strdup; jmp rax  (a tail call: the caller frees the copy)
    code = (b"\x48\xbf" + struct.pack("<Q", ctypes.addressof(_pocl_cpu_name_buffer))
            + b"\x48\xb8" + struct.pack("<Q", strdup) + b"\xff\xe0")
    page = addr & ~(mmap.PAGESIZE - 1)
    span = (addr + len(code) - page + mmap.PAGESIZE - 1) // mmap.PAGESIZE * mmap.PAGESIZE
    libc.mprotect.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    if libc.mprotect(ctypes.c_void_p(page), span, 7) != 0:
        _pocl_cpu_name_buffer = None
        return None
    ctypes.memmove(addr, code, len(code))
    libc.mprotect(ctypes.c_void_p(page), span, 5)
    return name
