"""NVIDIA Warp backend: every kernel function of `base.Backend` on `cpu` or `cuda:N`.

Kernels live in `relicgpu.kernels.warp` (kernels/warp/*.py), each named as the
function that launches it; this module moves numpy arrays to the device and back
and does the small host-side steps (flag intervals, grid sizing, final float64
sums). Same functions, signatures and return types as `relicgpu.backends.numpy`.
Warp compiles each kernel module once per device and caches the binary on disk
(~/.cache/warp).
"""
from __future__ import annotations

import threading

import numpy as np

from ._prep import (LcsBatch, PpfVotes, beyond_reach, centred_float32, check_edge_faces, check_faces,
                    choose_cell_size, flag_intervals, grid_dims, grid_reach2, nn_source, nn_target, parallel_copy)

# Warp's CPU device runs a launch on one thread; brute force beats building a
# grid below these many (source x target) pairs.
_BRUTE_PAIRS = {"cpu": 2_000_000, "cuda": 50_000_000}
_REDUCE_THREADS = {"cpu": 64, "cuda": 8192}
# ppf_votes: scratch rows (one per thread); the CPU device runs a launch on one thread
_PPF_ROWS = {"cpu": 1, "cuda": 1 << 16}
_PPF_SCRATCH_BYTES = {"cpu": 1 << 28, "cuda": 1 << 30}


def _quiet_warp(wp) -> None:
    """No banner and no per-module load lines on stdout (they would mix with CLI output)."""
    wp.config.quiet = True
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)


class WarpBackend:
    def __init__(self, device: str):
        import warp as wp

        _quiet_warp(wp)
        wp.init()
        dev = wp.get_device(device)  # raises for a device that is not there
        if dev.is_cuda and not wp.is_cuda_available():
            raise RuntimeError("no CUDA driver")
        self.wp = wp
        self.device = str(dev.alias)
        self.kind = "cpu" if dev.is_cpu else "cuda"
        self.name = "warp-cpu" if dev.is_cpu else f"warp-cuda:{dev.ordinal}"
        self.device_name = dev.name if dev.is_cuda else "CPU (one thread per launch)"
        from relicgpu.kernels.warp import curvature, icp, lcs, mosaic, normals, ppf

        self._k_normals, self._k_curv, self._k_lcs, self._k_icp = normals, curvature, lcs, icp
        self._k_mosaic, self._k_ppf = mosaic, ppf
        self._staging: dict[str, object] = {}  # pinned host buffers for large uploads (CUDA)
        self._staging_lock = threading.Lock()

    def __repr__(self) -> str:
        return f"WarpBackend({self.device!r})"

    # --- helpers -----------------------------------------------------------------

    def _array(self, data, dtype):
        return self.wp.array(data, dtype=dtype, device=self.device)

    def _upload_vec3d(self, points: np.ndarray, slot: str):
        """(N,3) float64 to a device vec3d array. Large arrays go to CUDA through a
        pinned staging buffer filled by several threads: a pageable copy ran at about
        6 GB/s on the H100 host, a pinned one at about 48 GB/s. Call with
        `_staging_lock` held; the copy is asynchronous and ordered before later launches."""
        wp = self.wp
        if self.kind != "cuda" or points.nbytes < (4 << 20):
            return self._array(points, wp.vec3d)
        n = len(points)
        buf = self._staging.get(slot)
        if buf is None or buf.shape[0] < n:
            buf = wp.empty(max(n, int(1.25 * (buf.shape[0] if buf is not None else 0))), dtype=wp.vec3d,
                           device="cpu", pinned=True)
            self._staging[slot] = buf
        parallel_copy(buf.numpy()[:n], points)
        out = wp.empty(n, dtype=wp.vec3d, device=self.device)
        wp.copy(out, buf, count=n)
        return out

    def _launch(self, kernel, dim, inputs):
        self.wp.launch(kernel, dim=dim, inputs=inputs, device=self.device)

    # --- normals -----------------------------------------------------------------

    def face_normals(self, vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        wp = self.wp
        v = centred_float32(vertices)
        f = check_faces(faces, len(v))
        if len(f) == 0:
            return np.zeros((0, 3)), np.zeros(0)
        normals = wp.empty(len(f), dtype=wp.vec3, device=self.device)
        areas = wp.empty(len(f), dtype=wp.float32, device=self.device)
        self._launch(self._k_normals.face_normals, len(f),
                     [self._array(v, wp.vec3), self._array(f, wp.vec3i), normals, areas])
        return normals.numpy().astype(np.float64), areas.numpy().astype(np.float64)

    def edge_angles(self, normals: np.ndarray, edge_faces: np.ndarray) -> np.ndarray:
        wp = self.wp
        n = np.ascontiguousarray(np.asarray(normals, np.float64).reshape(-1, 3), np.float32)
        e = check_edge_faces(edge_faces, len(n))
        if len(e) == 0:
            return np.zeros(0)
        out = wp.empty(len(e), dtype=wp.float32, device=self.device)
        self._launch(self._k_normals.edge_angles, len(e),
                     [self._array(n, wp.vec3), self._array(e, wp.vec2i), out])
        return out.numpy().astype(np.float64)

    # --- curvature ---------------------------------------------------------------

    def contour_features(self, points: np.ndarray, k: int, stride: int) -> np.ndarray:
        wp = self.wp
        p = np.ascontiguousarray(np.asarray(points, np.float64).reshape(-1, 3))
        if len(p) == 0:
            return np.zeros((0, 5))
        out = wp.empty((len(p), 5), dtype=wp.float64, device=self.device)
        self._launch(self._k_curv.contour_features, len(p),
                     [self._array(p, wp.vec3d), int(k), int(stride), out])
        return out.numpy()

    # --- flags and LCS -----------------------------------------------------------

    def flag_matrix(self, a: np.ndarray, b: np.ndarray, eps: float) -> np.ndarray:
        wp = self.wp
        a = np.asarray(a, np.float64).ravel()
        b = np.asarray(b, np.float64).ravel()
        if len(a) == 0 or len(b) == 0:
            return np.zeros((len(a), len(b)), bool)
        lo, hi = flag_intervals(a, eps)
        thr = np.ascontiguousarray(np.stack([lo, hi], 1))
        out = wp.empty((len(a), len(b)), dtype=wp.uint8, device=self.device)
        self._launch(self._k_lcs.flag_matrix, (len(a), len(b)),
                     [self._array(thr, wp.vec2), self._array(b.astype(np.float32), wp.float32), out])
        return out.numpy().astype(bool)

    def lcs_lengths(self, a_values, a_offsets, b_values, b_offsets, pairs, eps: float) -> np.ndarray:
        batch = LcsBatch(a_values, a_offsets, b_values, b_offsets, pairs, eps,
                               sort_pairs=self.kind == "cuda")
        if batch.n_pairs == 0:
            return np.zeros(0, np.int32)
        return batch.unsort(self.lcs_run(self.lcs_upload(batch)).numpy())

    def lcs_upload(self, batch: "LcsBatch") -> dict:
        """The device arrays of a prepared batch (split out so a benchmark can time the kernel alone)."""
        wp = self.wp
        return {"n_pairs": batch.n_pairs,
                "args": [self._array(batch.thr, wp.vec2), self._array(batch.a_off, wp.int32),
                         self._array(batch.b32, wp.float32), self._array(batch.b_off, wp.int32),
                         self._array(batch.pairs, wp.vec2i),
                         wp.empty(batch.carry_words(), dtype=wp.uint32, device=self.device)]}

    def lcs_run(self, uploaded: dict):
        """Launch the LCS kernel on uploaded arrays; returns the device array of lengths."""
        wp = self.wp
        n = uploaded["n_pairs"]
        out = wp.empty(n, dtype=wp.int32, device=self.device)
        # one thread per pair and few pairs per block, so that a batch of ~10^4 pairs
        # still spreads over every multiprocessor of a large GPU
        wp.launch(self._k_lcs.lcs_lengths, dim=n, inputs=[*uploaded["args"], n, out],
                  device=self.device, block_dim=32 if self.kind == "cuda" else 256)
        return out

    # --- nearest neighbours and reductions ---------------------------------------

    def nearest_neighbors(self, source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.nearest_index(target).query(source)

    def nearest_index(self, target: np.ndarray) -> "WarpNearestIndex":
        """The target uploaded and (when queries need it) sorted into a grid once, for many queries."""
        dst = nn_target(target)
        with self._staging_lock:
            return WarpNearestIndex(self, self._upload_vec3d(dst, "target"))

    def _bounds(self, points_d):
        """float64 (lo, hi) of finite points; raises on NaN or infinite coordinates."""
        wp = self.wp
        n = points_d.shape[0]
        threads = min(n, _REDUCE_THREADS[self.kind])
        lo = wp.empty(threads, dtype=wp.vec3d, device=self.device)
        hi = wp.empty(threads, dtype=wp.vec3d, device=self.device)
        bad = wp.empty(threads, dtype=wp.int32, device=self.device)
        self._launch(self._k_icp.bounds_partial, threads, [points_d, n, lo, hi, bad])
        if bad.numpy().sum():
            raise ValueError("nearest_neighbors: points with NaN or infinite coordinates")
        return lo.numpy().min(0), hi.numpy().max(0)

    def nearest_neighbors_device(self, src_d, dst_d):
        """Nearest neighbours of device arrays (vec3d); returns device arrays (idx int32, dist float64)."""
        self._bounds(src_d)
        return WarpNearestIndex(self, dst_d).query_device(src_d)

    def cross_covariance(self, source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None):
        wp = self.wp
        s = np.ascontiguousarray(np.asarray(source, np.float64).reshape(-1, 3))
        t = np.ascontiguousarray(np.asarray(target, np.float64).reshape(-1, 3))
        if len(s) != len(t):
            raise ValueError(f"cross_covariance: {len(s)} source points but {len(t)} target points")
        w = np.ones(len(s)) if weights is None else np.ascontiguousarray(np.asarray(weights, np.float64).ravel())
        if len(w) != len(s):
            raise ValueError(f"cross_covariance: {len(w)} weights for {len(s)} point pairs")
        n = len(s)
        if n == 0:
            return np.zeros(3), np.zeros(3), np.zeros((3, 3)), 0.0
        threads = min(n, _REDUCE_THREADS[self.kind])
        s_d, t_d, w_d = self._array(s, wp.vec3d), self._array(t, wp.vec3d), self._array(w, wp.float64)
        part = wp.empty((threads, 7), dtype=wp.float64, device=self.device)
        self._launch(self._k_icp.weighted_sums_partial, threads, [s_d, t_d, w_d, n, part])
        sums = part.numpy().sum(0)
        wsum = float(sums[0])
        if wsum <= 0:
            return np.zeros(3), np.zeros(3), np.zeros((3, 3)), 0.0
        cs, ct = sums[1:4] / wsum, sums[4:7] / wsum
        part = wp.empty((threads, 9), dtype=wp.float64, device=self.device)
        self._launch(self._k_icp.covariance_partial, threads,
                     [s_d, t_d, w_d, wp.vec3d(*cs), wp.vec3d(*ct), n, part])
        h = part.numpy().sum(0).reshape(3, 3)
        return cs, ct, h, wsum

    # --- point-pair-feature votes -------------------------------------------------

    def ppf_votes(self, model_start, model_ref, model_alpha, model_weight, scene_key, scene_ref, scene_alpha,
                  scene_weight, n_refs: int, n_model: int, alpha_bins: int, bucket_cap: int):
        wp = self.wp
        b = PpfVotes(model_start, model_ref, model_alpha, model_weight, scene_key, scene_ref, scene_alpha,
                     scene_weight, n_refs, n_model, alpha_bins, bucket_cap)
        if b.n_refs == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        threads = b.rows_in_flight(_PPF_ROWS[self.kind], _PPF_SCRATCH_BYTES[self.kind])
        rows = wp.zeros((threads, b.row), dtype=wp.float64, device=self.device)
        touched = wp.empty((threads, b.touched_width + 1), dtype=wp.int32, device=self.device)
        cell = wp.empty(b.n_refs, dtype=wp.int32, device=self.device)
        votes = wp.empty(b.n_refs, dtype=wp.float64, device=self.device)
        shift, scale = b.angle_constants()
        start, records = b.voting_model()
        self._launch(self._k_ppf.ppf_votes, threads, [
            self._array(start, wp.int32), len(start) - 2, self._array(records, wp.vec3),
            self._array(b.s_offsets.astype(np.int32), wp.int32), self._array(b.s_key, wp.int64),
            self._array(b.s_alpha, wp.float32), self._array(b.scene_weight_or_ones(), wp.float32), b.n_refs,
            b.alpha_bins, float(shift), float(scale), threads, rows, touched, cell, votes])
        return cell.numpy().astype(np.int64), votes.numpy()

    # --- the mosaic's kernels ----------------------------------------------------

    def led(self, image: np.ndarray, half: int) -> np.ndarray:
        wp = self.wp
        src = np.ascontiguousarray(image, np.float32)
        h, w = src.shape
        rows = wp.empty((h, w), dtype=wp.float32, device=self.device)
        out = wp.empty((h, w), dtype=wp.float32, device=self.device)
        self._launch(self._k_mosaic.led_rows, (h, w), [self._array(src, wp.float32), int(half), rows])
        self._launch(self._k_mosaic.led_cols, (h, w), [rows, int(half), 1.0 / float((2 * half + 1) ** 2), out])
        return out.numpy()

    def block_entropy(self, levels: np.ndarray, block: int, n_levels: int) -> np.ndarray:
        wp = self.wp
        src = np.ascontiguousarray(levels, np.float32)
        h, w = src.shape
        out = wp.empty((h - block + 1, w - block + 1), dtype=wp.float32, device=self.device)
        self._launch(self._k_mosaic.block_entropy, out.shape,
                     [self._array(src, wp.float32), int(block), int(n_levels), out])
        return out.numpy()


    # --- benchmarks (base.DeviceTiming) ---------------------------------------------

    def device_kernel(self, family: str, *inputs):
        """On CUDA, a callable that runs the "lcs" or "nearest" kernels on `inputs` uploaded
        once and waits for the device (the kernel alone, transfers left out); None on the CPU."""
        if self.kind != "cuda":
            return None
        wp = self.wp
        if family == "lcs":
            uploaded = self.lcs_upload(LcsBatch(*inputs, sort_pairs=True))

            def run():
                self.lcs_run(uploaded)
                wp.synchronize_device(self.device)
        elif family == "nearest":
            source, target = inputs
            s_d, d_d = wp.array(source, dtype=wp.vec3d, device=self.device), wp.array(target, dtype=wp.vec3d,
                                                                                        device=self.device)

            def run():
                self.nearest_neighbors_device(s_d, d_d)
                wp.synchronize_device(self.device)
        else:
            raise ValueError(f"device_kernel: unknown family {family!r}; choose lcs or nearest")
        return run

class WarpNearestIndex:
    """A target point set on the device for repeated nearest-neighbour queries (an ICP's
    rounds): uploaded, bounded and shifted once; its grid built at the first query that
    needs one. `query` gives what `nearest_neighbors(source, target)` gives."""

    def __init__(self, backend: WarpBackend, dst_d):
        wp = backend.wp
        self.be, self.dst_d, self.n = backend, dst_d, dst_d.shape[0]
        lo, hi = backend._bounds(dst_d)
        self.centre = 0.5 * (lo + hi)
        self.origin, self.extent = lo - self.centre, hi - lo
        self.dst32 = wp.empty(self.n, dtype=wp.vec3, device=backend.device)
        backend._launch(backend._k_icp.shift_to_float32, self.n, [dst_d, wp.vec3d(*self.centre), self.dst32])
        self.grid = None  # (h, dims, starts, sorted points, sorted ids)
        self._counts = None  # per-cell counts, then the scatter's cursors

    def query(self, source: np.ndarray, within: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        src = nn_source(source)
        if len(src) == 0:
            return np.zeros(0, np.int32), np.zeros(0)
        with self.be._staging_lock:  # the staging buffers are reused once the results are back
            idx, dist = self.query_device(self.be._upload_vec3d(src, "source"), within)
            return beyond_reach(idx.numpy(), self.n), dist.numpy()

    def query_device(self, src_d, within: float | None = None):
        be, wp, k = self.be, self.be.wp, self.be._k_icp
        ns = src_d.shape[0]
        src32 = wp.empty(ns, dtype=wp.vec3, device=be.device)
        be._launch(k.shift_to_float32, ns, [src_d, wp.vec3d(*self.centre), src32])
        idx = wp.empty(ns, dtype=wp.int32, device=be.device)
        if ns * self.n <= _BRUTE_PAIRS[be.kind] or self.n <= 64:
            be._launch(k.brute_query, ns, [src32, self.dst32, idx])
        else:
            if self.grid is None:
                self.grid = self._build_grid()
            h, dims, starts, sorted_points, sorted_ids = self.grid
            _, sorted_queries, query_ids = self._sort_into_cells(src32, h)
            be._launch(k.grid_query, ns, [sorted_queries, query_ids, wp.vec3(*self.origin), float(h), 1.0 / h, dims,
                                          starts, sorted_points, sorted_ids, grid_reach2(within, self.extent), idx])
        dist = wp.empty(ns, dtype=wp.float64, device=be.device)
        be._launch(k.exact_distance, ns, [src_d, self.dst_d, idx, dist])
        return idx, dist

    def _count(self, points, h: float, occupied=None) -> int:
        be, wp = self.be, self.be.wp
        dims = grid_dims(self.extent, h)
        cells = int(np.prod(dims))
        if self._counts is None or self._counts.shape[0] < cells + 1:
            self._counts = wp.zeros(cells + 1, dtype=wp.int32, device=be.device)
        else:
            self._counts.zero_()
        if occupied is None:
            occupied = wp.zeros(1, dtype=wp.int32, device=be.device)
        be._launch(be._k_icp.grid_count, points.shape[0],
                   [points, wp.vec3(*self.origin), 1.0 / h, wp.vec3i(*dims), self._counts, occupied])
        return cells

    def _sort_into_cells(self, points, h: float):
        be, wp = self.be, self.be.wp
        cells = self._count(points, h)
        dims = wp.vec3i(*grid_dims(self.extent, h))
        starts = wp.empty(cells + 1, dtype=wp.int32, device=be.device)
        wp.utils.array_scan(self._counts[: cells + 1], starts, inclusive=False)
        self._counts.zero_()
        sorted_points = wp.empty(points.shape[0], dtype=wp.vec3, device=be.device)
        sorted_ids = wp.empty(points.shape[0], dtype=wp.int32, device=be.device)
        be._launch(be._k_icp.grid_scatter, points.shape[0], [points, wp.vec3(*self.origin), 1.0 / h, dims, starts,
                                                             self._counts, sorted_points, sorted_ids])
        return starts, sorted_points, sorted_ids

    def _build_grid(self):
        wp = self.be.wp
        occupied = wp.zeros(1, dtype=wp.int32, device=self.be.device)

        def occupied_at(h: float) -> int:
            occupied.zero_()
            self._count(self.dst32, h, occupied)
            return int(occupied.numpy()[0])

        h = choose_cell_size(self.extent, self.n, occupied_at)
        starts, sorted_points, sorted_ids = self._sort_into_cells(self.dst32, h)
        return h, wp.vec3i(*grid_dims(self.extent, h)), starts, sorted_points, sorted_ids
