"""OpenCL backend (pyopencl): every kernel function of `base.Backend` on any OpenCL
platform, PoCL on a CPU (all cores) or a GPU vendor's driver.

Kernels live in `relicgpu.kernels.opencl` (kernels/opencl/*.cl), named as in
kernels/warp. `program(name)` builds a source once per process and caches it, with
device-dependent options (`-DHAVE_FP64` where the device has doubles; for lcs.cl on
CPUs, `-DRELIC_VECTOR_MASKS=16|8`, the widest vector width whose build passes the
LCS self-check). Same functions, signatures and return types as
`relicgpu.backends.numpy`.

Go through this module before anything else touches pyopencl's devices: listing the
platforms or making a backend first repairs PoCL's CPU detection on processors newer
than PoCL's LLVM (`pocl.repair_pocl_cpu_name`).
"""
from __future__ import annotations

import importlib.resources
import threading
from pathlib import Path

import numpy as np

from ._prep import (LcsBatch, PpfVotes, beyond_reach, centred_float32, check_edge_faces, check_faces,
                    choose_cell_size, flag_intervals, grid_dims, grid_reach2, nn_source, nn_target)
from .pocl import repair_pocl_cpu_name
from .selfcheck import check_family

_REDUCE_THREADS = {"cpu": 256, "gpu": 8192}
_LOCAL_2D = (16, 4)  # the work-group shape of the image kernels
_BRUTE_PAIRS = {"cpu": 4_000_000, "gpu": 50_000_000}
# ppf_votes: work-items (each a scratch row) per compute unit, work-group size, scratch bytes
_PPF_ROWS_PER_UNIT = {"cpu": 4, "gpu": 1 << 12}
_PPF_LOCAL = {"cpu": 1, "gpu": 64}
_PPF_SCRATCH_BYTES = {"cpu": 1 << 28, "gpu": 1 << 30}




def platform_names() -> list[str]:
    """Names of the OpenCL platforms that have at least one device."""
    repair_pocl_cpu_name()
    import pyopencl as cl

    names = []
    for p in cl.get_platforms():
        try:
            if p.get_devices():
                names.append(p.name)
        except cl.Error:
            continue
    return names


def _pick_platform(cl, wanted: str | None):
    platforms = cl.get_platforms()
    if not platforms:
        raise RuntimeError("no OpenCL platform is installed")
    if wanted is None:
        for p in platforms:
            try:
                if p.get_devices():
                    return p
            except cl.Error:
                continue
        raise RuntimeError("no OpenCL platform has a device")
    for p in platforms:
        if p.name == wanted:
            return p
    for p in platforms:
        if wanted.lower() in p.name.lower():
            return p
    raise RuntimeError(f"no OpenCL platform named {wanted!r}; found {[p.name for p in platforms]}")


class OpenCLBackend:
    def __init__(self, platform: str | None = None, lcs_masks: int | None = None):
        """The first device (a GPU where there is one) of `platform` (a name or part of one;
        None: the first platform with a device). `lcs_masks` forces the LCS kernel's
        vector width (16, 8 or 0 for scalar); by default a CPU takes the widest whose
        build passes the LCS self-check, a GPU the scalar kernel."""
        repair_pocl_cpu_name()
        import pyopencl as cl

        self.cl = cl
        plat = _pick_platform(cl, platform)
        devices = plat.get_devices()
        gpus = [d for d in devices if d.type & cl.device_type.GPU]
        self.device = (gpus or devices)[0]
        self.kind = "gpu" if self.device.type & cl.device_type.GPU else "cpu"
        self.ctx = cl.Context([self.device])
        self.queue = cl.CommandQueue(self.ctx)
        self.platform_name = plat.name
        self.name = f"opencl:{plat.name}"
        self.device_name = self.device.name.strip()
        self.has_fp64 = bool(self.device.double_fp_config)
        self.local_size = min(64 if self.kind == "cpu" else 128, self.device.max_work_group_size)
        self.real = np.float64 if self.has_fp64 else np.float32
        self._programs: dict[tuple[str, str], object] = {}
        self._kernels: dict[tuple[str, str, str], object] = {}
        self._lock = threading.RLock()  # kernel objects hold their arguments: one caller at a time
        self.lcs_masks = lcs_masks if lcs_masks is not None else (None if self.kind == "cpu" else 0)
        self.lcs_masks_refused: dict[int, str] = {}  # width -> what its build got wrong

    def __repr__(self) -> str:
        return f"OpenCLBackend({self.platform_name!r})"

    # --- programs -----------------------------------------------------------------

    def default_options(self, source_filename: str | None = None) -> str:
        opts = []
        if self.has_fp64:
            opts.append("-DHAVE_FP64=1")
        if source_filename == "lcs.cl":
            opts.append(f"-DRELIC_VECTOR_MASKS={self._lcs_width()}")
        return " ".join(opts)

    def _lcs_width(self) -> int:
        """The LCS kernel's vector width: on a CPU, 16 then 8 are built and self-checked,
        and the first that agrees with the reference is kept (0, scalar, if neither)."""
        with self._lock:
            if self.lcs_masks is None:
                for width in (16, 8):
                    self.lcs_masks = width
                    why = check_family(self, "lcs")
                    if why is None:
                        return width
                    self.lcs_masks_refused[width] = why
                self.lcs_masks = 0
            return self.lcs_masks

    def program(self, source_filename: str, options: str | None = None):
        """The built program of a kernel source, compiled once per process.

        `source_filename` names a file of relicgpu.kernels.opencl (e.g. "lcs.cl")
        or is a path to any .cl file; `options` defaults to `default_options()`."""
        options = self.default_options(str(source_filename)) if options is None else options
        key = (str(source_filename), options)
        with self._lock:
            prog = self._programs.get(key)
            if prog is None:
                path = Path(source_filename)
                if path.is_absolute():
                    source = path.read_text()
                else:
                    source = importlib.resources.files("relicgpu.kernels.opencl").joinpath(str(path)).read_text()
                prog = self.cl.Program(self.ctx, source).build(options=options.split())
                self._programs[key] = prog
            return prog

    def kernel(self, source_filename: str, name: str):
        options = self.default_options(source_filename)
        key = (source_filename, options, name)
        k = self._kernels.get(key)
        if k is None:
            k = self.cl.Kernel(self.program(source_filename, options), name)
            self._kernels[key] = k
        return k

    # --- helpers ------------------------------------------------------------------

    def _to_device(self, array: np.ndarray):
        mf = self.cl.mem_flags
        a = np.ascontiguousarray(array)
        if a.nbytes == 0:
            a = np.zeros(1, a.dtype)
        return self.cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)

    def _empty(self, nbytes: int):
        return self.cl.Buffer(self.ctx, self.cl.mem_flags.READ_WRITE, size=max(int(nbytes), 4))

    def _from_device(self, buf, shape, dtype) -> np.ndarray:
        out = np.empty(shape, dtype)
        if out.size:
            self.cl.enqueue_copy(self.queue, out, buf, is_blocking=True)
        return out

    def _run(self, source: str, name: str, n: int, *args, local: int | None = None):
        """Enqueue kernel `name` over n work-items, padded to whole work-groups (the kernels
        check their bounds). A fixed work-group size matters on PoCL, which compiles a
        kernel anew for every work-group size it meets. `args` stay referenced until the
        enqueue: OpenCL retains a buffer only once it is enqueued."""
        k = self.kernel(source, name)
        k.set_args(*args)
        local = local or self.local_size
        size = max((n + local - 1) // local * local, local)
        self.cl.enqueue_nd_range_kernel(self.queue, k, (size,), (local,))

    def _run_2d(self, source: str, name: str, width: int, height: int, *args):
        """`_run` over a width x height grid of work-items (get_global_id(0) the column)."""
        k = self.kernel(source, name)
        k.set_args(*args)
        size = tuple(max(-(-n // g) * g, g) for n, g in zip((width, height), _LOCAL_2D))
        self.cl.enqueue_nd_range_kernel(self.queue, k, size, _LOCAL_2D)

    # --- normals ------------------------------------------------------------------

    def face_normals(self, vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        v = centred_float32(vertices)
        f = check_faces(faces, len(v))
        if len(f) == 0:
            return np.zeros((0, 3)), np.zeros(0)
        with self._lock:
            normals = self._empty(12 * len(f))
            areas = self._empty(4 * len(f))
            self._run("normals.cl", "face_normals", len(f), self._to_device(v), self._to_device(f),
                      np.int32(len(f)), normals, areas)
            n = self._from_device(normals, (len(f), 3), np.float32)
            a = self._from_device(areas, len(f), np.float32)
        return n.astype(np.float64), a.astype(np.float64)

    def edge_angles(self, normals: np.ndarray, edge_faces: np.ndarray) -> np.ndarray:
        n = np.ascontiguousarray(np.asarray(normals, np.float64).reshape(-1, 3), np.float32)
        e = check_edge_faces(edge_faces, len(n))
        if len(e) == 0:
            return np.zeros(0)
        with self._lock:
            out = self._empty(4 * len(e))
            self._run("normals.cl", "edge_angles", len(e), self._to_device(n), self._to_device(e),
                      np.int32(len(e)), out)
            return self._from_device(out, len(e), np.float32).astype(np.float64)

    # --- curvature ----------------------------------------------------------------

    def contour_features(self, points: np.ndarray, k: int, stride: int) -> np.ndarray:
        p = np.ascontiguousarray(np.asarray(points, np.float64).reshape(-1, 3), self.real)
        if len(p) == 0:
            return np.zeros((0, 5))
        with self._lock:
            out = self._empty(5 * len(p) * p.itemsize)
            self._run("curvature.cl", "contour_features", len(p), self._to_device(p), np.int32(len(p)),
                      np.int32(k), np.int32(stride), out)
            return self._from_device(out, (len(p), 5), self.real).astype(np.float64)

    # --- flags and LCS ------------------------------------------------------------

    def flag_matrix(self, a: np.ndarray, b: np.ndarray, eps: float) -> np.ndarray:
        a = np.asarray(a, np.float64).ravel()
        b = np.asarray(b, np.float64).ravel()
        if len(a) == 0 or len(b) == 0:
            return np.zeros((len(a), len(b)), bool)
        lo, hi = flag_intervals(a, eps)
        thr = np.ascontiguousarray(np.stack([lo, hi], 1))
        with self._lock:
            out = self._empty(len(a) * len(b))
            args = (self._to_device(thr), self._to_device(b.astype(np.float32)), np.int32(len(a)),
                    np.int32(len(b)), out)  # held until enqueued: a released buffer must not reach the kernel
            k = self.kernel("lcs.cl", "flag_matrix")
            k.set_args(*args)
            cols = (len(b) + self.local_size - 1) // self.local_size * self.local_size
            self.cl.enqueue_nd_range_kernel(self.queue, k, (cols, len(a)), (self.local_size, 1))
            return self._from_device(out, (len(a), len(b)), np.uint8).astype(bool)

    def lcs_lengths(self, a_values, a_offsets, b_values, b_offsets, pairs, eps: float) -> np.ndarray:
        batch = LcsBatch(a_values, a_offsets, b_values, b_offsets, pairs, eps,
                               sort_pairs=self.kind == "gpu")
        if batch.n_pairs == 0:
            return np.zeros(0, np.int32)
        with self._lock:
            out = self._empty(4 * batch.n_pairs)
            carry = self._empty(4 * batch.carry_words())
            self._run("lcs.cl", "lcs_lengths", batch.n_pairs,
                      self._to_device(batch.thr), self._to_device(batch.a_off), self._to_device(batch.b32),
                      self._to_device(batch.b_off), self._to_device(batch.pairs), carry,
                      np.int32(batch.n_pairs), out)
            lengths = self._from_device(out, batch.n_pairs, np.int32)
        return batch.unsort(lengths)

    # --- nearest neighbours and reductions ----------------------------------------

    def nearest_neighbors(self, source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.nearest_index(target).query(source)

    def nearest_index(self, target: np.ndarray) -> "OpenCLNearestIndex":
        """The target uploaded and (when queries need it) sorted into a grid once, for many queries."""
        dst = nn_target(target)
        return OpenCLNearestIndex(self, dst)

    def _bounds(self, points_d, n: int):
        threads = min(n, _REDUCE_THREADS[self.kind])
        lo, hi = self._empty(24 * threads), self._empty(24 * threads)
        bad = self._empty(4 * threads)
        self._run("icp.cl", "bounds_partial", threads, points_d, np.int32(n), np.int32(threads), lo, hi, bad)
        if self._from_device(bad, threads, np.int32).sum():
            raise ValueError("nearest_neighbors: points with NaN or infinite coordinates")
        lo = self._from_device(lo, (threads, 3), self.real).astype(np.float64)
        hi = self._from_device(hi, (threads, 3), self.real).astype(np.float64)
        return lo.min(0), hi.max(0)

    def cross_covariance(self, source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None):
        s = np.asarray(source, np.float64).reshape(-1, 3)
        t = np.asarray(target, np.float64).reshape(-1, 3)
        if len(s) != len(t):
            raise ValueError(f"cross_covariance: {len(s)} source points but {len(t)} target points")
        w = np.ones(len(s)) if weights is None else np.asarray(weights, np.float64).ravel()
        if len(w) != len(s):
            raise ValueError(f"cross_covariance: {len(w)} weights for {len(s)} point pairs")
        n = len(s)
        if n == 0:
            return np.zeros(3), np.zeros(3), np.zeros((3, 3)), 0.0
        threads = min(n, _REDUCE_THREADS[self.kind])
        r = self.real
        with self._lock:
            s_d, t_d, w_d = (self._to_device(x.astype(r, copy=False)) for x in (s, t, w))
            part = self._empty(7 * threads * np.dtype(r).itemsize)
            self._run("icp.cl", "weighted_sums_partial", threads, s_d, t_d, w_d, np.int32(n), np.int32(threads), part)
            sums = self._from_device(part, (threads, 7), r).astype(np.float64).sum(0)
            wsum = float(sums[0])
            if wsum <= 0:
                return np.zeros(3), np.zeros(3), np.zeros((3, 3)), 0.0
            cs, ct = sums[1:4] / wsum, sums[4:7] / wsum
            part = self._empty(9 * threads * np.dtype(r).itemsize)
            self._run("icp.cl", "covariance_partial", threads, s_d, t_d, w_d, *[r(x) for x in cs],
                      *[r(x) for x in ct], np.int32(n), np.int32(threads), part)
            h = self._from_device(part, (threads, 9), r).astype(np.float64).sum(0).reshape(3, 3)
        return cs, ct, h, wsum

    # --- point-pair-feature votes ---------------------------------------------------

    def ppf_votes(self, model_start, model_ref, model_alpha, model_weight, scene_key, scene_ref, scene_alpha,
                  scene_weight, n_refs: int, n_model: int, alpha_bins: int, bucket_cap: int):
        b = PpfVotes(model_start, model_ref, model_alpha, model_weight, scene_key, scene_ref, scene_alpha,
                     scene_weight, n_refs, n_model, alpha_bins, bucket_cap)
        if b.n_refs == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        r = self.real
        size = np.dtype(r).itemsize
        threads = b.rows_in_flight(_PPF_ROWS_PER_UNIT[self.kind] * self.device.max_compute_units,
                                   _PPF_SCRATCH_BYTES[self.kind], size)
        shift, scale = b.angle_constants()
        start, records = b.voting_model()
        with self._lock:
            rows = self._empty(threads * b.row * size)
            self.cl.enqueue_fill_buffer(self.queue, rows, r(0), 0, threads * b.row * size)
            cell, votes = self._empty(4 * b.n_refs), self._empty(size * b.n_refs)
            self._run("ppf.cl", "ppf_votes", threads, self._to_device(start), np.int64(len(start) - 2),
                      self._to_device(records), self._to_device(b.s_offsets.astype(np.int32)),
                      self._to_device(b.s_key), self._to_device(b.s_alpha), self._to_device(b.scene_weight_or_ones()),
                      np.int32(b.n_refs), np.int32(b.alpha_bins), shift, scale, np.int32(threads), np.int32(b.row),
                      rows, np.int32(b.touched_width), self._empty(4 * threads * (b.touched_width + 1)), cell, votes,
                      local=_PPF_LOCAL[self.kind])
            best = self._from_device(cell, b.n_refs, np.int32).astype(np.int64)
            return best, self._from_device(votes, b.n_refs, r).astype(np.float64)

    # --- the mosaic's kernels -----------------------------------------------------

    def led(self, image: np.ndarray, half: int) -> np.ndarray:
        src = np.ascontiguousarray(image, np.float32)
        h, w = src.shape
        scale = 1.0 / float((2 * half + 1) ** 2)
        with self._lock:
            rows, out = self._empty(src.nbytes), self._empty(src.nbytes)
            self._run_2d("mosaic.cl", "led_rows", w, h, self._to_device(src), np.int32(h), np.int32(w),
                         np.int32(half), rows)
            self._run_2d("mosaic.cl", "led_cols", w, h, rows, np.int32(h), np.int32(w), np.int32(half),
                         np.float32(scale), out)
            return self._from_device(out, (h, w), np.float32)

    def block_entropy(self, levels: np.ndarray, block: int, n_levels: int) -> np.ndarray:
        src = np.ascontiguousarray(levels, np.float32)
        h, w = src.shape
        oh, ow = h - block + 1, w - block + 1
        with self._lock:
            out = self._empty(4 * oh * ow)
            self._run_2d("mosaic.cl", "block_entropy", ow, oh, self._to_device(src), np.int32(h), np.int32(w),
                         np.int32(block), np.int32(n_levels), out)
            return self._from_device(out, (oh, ow), np.float32)


class OpenCLNearestIndex:
    """A target point set on the device for repeated nearest-neighbour queries (an ICP's
    rounds): uploaded, bounded and shifted once; its grid built at the first query that
    needs one. `query` gives what `nearest_neighbors(source, target)` gives."""

    def __init__(self, backend: OpenCLBackend, dst: np.ndarray):
        self.be, self.n = backend, len(dst)
        with backend._lock:
            self.dst_d = backend._to_device(dst.astype(backend.real, copy=False))
            lo, hi = backend._bounds(self.dst_d, self.n)
            self.centre = 0.5 * (lo + hi)
            self.origin, self.extent = lo - self.centre, hi - lo
            self.dst32 = backend._empty(12 * self.n)
            backend._run("icp.cl", "shift_to_float32", self.n, self.dst_d, np.int32(self.n),
                         *[backend.real(x) for x in self.centre], self.dst32)
        self.grid = None  # (h, dims, starts, sorted points, sorted ids)
        self._counts, self._cells = None, 0  # per-cell counts, then the scatter's cursors
        self._occupied = None

    def query(self, source: np.ndarray, within: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        be = self.be
        src = nn_source(source)
        ns = len(src)
        if ns == 0:
            return np.zeros(0, np.int32), np.zeros(0)
        with be._lock:
            src_d = be._to_device(src.astype(be.real, copy=False))
            src32 = be._empty(12 * ns)
            be._run("icp.cl", "shift_to_float32", ns, src_d, np.int32(ns), *[be.real(x) for x in self.centre], src32)
            idx = be._empty(4 * ns)
            if ns * self.n <= _BRUTE_PAIRS[be.kind] or self.n <= 64:
                be._run("icp.cl", "brute_query", ns, src32, np.int32(ns), self.dst32, np.int32(self.n), idx,
                        local=min(128, be.local_size))
            else:
                if self.grid is None:
                    self.grid = self._build_grid()
                h, dims, starts, sorted_points, sorted_ids = self.grid
                _, sorted_queries, query_ids = self._sort_into_cells(src32, ns, h)
                be._run("icp.cl", "grid_query", ns, sorted_queries, query_ids, np.int32(ns), *self._o(),
                        np.float32(h), np.float32(1.0 / h), *[np.int32(d) for d in dims], starts, sorted_points,
                        sorted_ids, np.float32(grid_reach2(within, self.extent)), idx)
            dist = be._empty(np.dtype(be.real).itemsize * ns)
            be._run("icp.cl", "exact_distance", ns, src_d, self.dst_d, idx, np.int32(ns), dist)
            return (beyond_reach(be._from_device(idx, ns, np.int32), self.n),
                    be._from_device(dist, ns, be.real).astype(np.float64))

    def _o(self):
        return [np.float32(x) for x in self.origin]

    def _count(self, points, n: int, h: float):
        be, cl = self.be, self.be.cl
        dims = grid_dims(self.extent, h)
        cells = int(np.prod(dims))
        if self._counts is None or self._cells < cells + 1:
            self._counts, self._cells = be._empty(4 * (cells + 1)), cells + 1
        if self._occupied is None:
            self._occupied = be._empty(4)
        cl.enqueue_fill_buffer(be.queue, self._counts, np.int32(0), 0, 4 * (cells + 1))
        cl.enqueue_fill_buffer(be.queue, self._occupied, np.int32(0), 0, 4)
        be._run("icp.cl", "grid_count", n, points, np.int32(n), *self._o(), np.float32(1.0 / h),
                *[np.int32(d) for d in dims], self._counts, self._occupied)
        return cells, dims

    def _sort_into_cells(self, points, n: int, h: float):
        be, cl = self.be, self.be.cl
        cells, dims = self._count(points, n, h)
        counts = be._from_device(self._counts, cells, np.int32)
        starts = np.zeros(cells + 1, np.int32)
        np.cumsum(counts, out=starts[1:])
        starts_d = be._to_device(starts)
        cl.enqueue_fill_buffer(be.queue, self._counts, np.int32(0), 0, 4 * (cells + 1))
        sorted_points, sorted_ids = be._empty(12 * n), be._empty(4 * n)
        be._run("icp.cl", "grid_scatter", n, points, np.int32(n), *self._o(), np.float32(1.0 / h),
                *[np.int32(d) for d in dims], starts_d, self._counts, sorted_points, sorted_ids)
        return starts_d, sorted_points, sorted_ids

    def _build_grid(self):
        be = self.be

        def occupied_at(h: float) -> int:
            self._count(self.dst32, self.n, h)
            return int(be._from_device(self._occupied, 1, np.int32)[0])

        h = choose_cell_size(self.extent, self.n, occupied_at)
        starts, sorted_points, sorted_ids = self._sort_into_cells(self.dst32, self.n, h)
        return h, grid_dims(self.extent, h), starts, sorted_points, sorted_ids
