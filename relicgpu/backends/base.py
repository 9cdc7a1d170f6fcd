"""The backend contract: every kernel function a backend offers.

`relicgpu.backends.numpy` (a module, float64) is the specification; `WarpBackend` and
`OpenCLBackend` implement the same members with the same signatures, NumPy arrays in
and out, and are self-checked against it (`selfcheck`). Code outside
`relicgpu.backends` calls these members only (a benchmark also `DeviceTiming`'s, where a
backend offers it).
"""
from __future__ import annotations

from typing import Callable, Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class NearestIndex(Protocol):
    """A target point set prepared once (uploaded, gridded) for many queries."""

    def query(self, source: np.ndarray, within: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """`nearest_neighbors(source, target)` for the prepared target.

        Parameters
        ----------
        source : (s, 3) float
        within : optional reach: a source point farther than this from the target may come back
            as (len(target), inf) instead of its nearest point (a k-d tree stops early; a
            backend may as well answer exactly)

        Returns
        -------
        index : (s,) int32
        distance : (s,) float64
        """
        ...


@runtime_checkable
class Backend(Protocol):
    """The kernel functions of a compute backend."""

    name: str  # as the registry names it: numpy, warp-cpu, warp-cuda:N, opencl:PLATFORM

    # --- normals -----------------------------------------------------------------

    def face_normals(self, vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unit normals and areas of triangles; a zero-area face gets a zero normal.

        Parameters
        ----------
        vertices : (v, 3) float
        faces : (f, 3) int
            Vertex indices.

        Returns
        -------
        normals : (f, 3) float64
        areas : (f,) float64
        """
        ...

    def edge_angles(self, normals: np.ndarray, edge_faces: np.ndarray) -> np.ndarray:
        """Angle between the normals of the two faces of every shared edge; 0 next to a
        zero normal.

        Parameters
        ----------
        normals : (f, 3) float
        edge_faces : (e, 2) int
            The two faces of each edge.

        Returns
        -------
        angles : (e,) float64
            Radians in [0, pi].
        """
        ...

    # --- curvature ---------------------------------------------------------------

    def contour_features(self, points: np.ndarray, k: int, stride: int) -> np.ndarray:
        """k-cosine curvature, discrete curvature and torsion, and the two chords at
        `stride`, per point of a closed contour (indices wrap around).

        Parameters
        ----------
        points : (n, 3) float
        k : int
            Scales 1..k of the k-cosine.
        stride : int
            Step of the finite differences and chords.

        Returns
        -------
        features : (n, 5) float64
            Columns kcos, kappa, tau, chord_right, chord_left.
        """
        ...

    # --- flags and LCS -----------------------------------------------------------

    def flag_matrix(self, a: np.ndarray, b: np.ndarray, eps: float) -> np.ndarray:
        """flags[i, j] = |a_i - b_j| < eps.

        Parameters
        ----------
        a : (m,) float
        b : (n,) float
        eps : float

        Returns
        -------
        flags : (m, n) bool
        """
        ...

    def lcs_lengths(self, a_values: np.ndarray, a_offsets: np.ndarray, b_values: np.ndarray,
                    b_offsets: np.ndarray, pairs: np.ndarray, eps: float) -> np.ndarray:
        """Longest-common-subsequence lengths of many sequence pairs, two values being
        equal when flagged (`flag_matrix`).

        Parameters
        ----------
        a_values : (total_a,) float
            Sequence i of a is a_values[a_offsets[i]:a_offsets[i + 1]].
        a_offsets : (count_a + 1,) int
        b_values : (total_b,) float
        b_offsets : (count_b + 1,) int
        pairs : (p, 2) int
            (sequence of a, sequence of b).
        eps : float

        Returns
        -------
        lengths : (p,) int32
        """
        ...

    # --- nearest neighbours and reductions -----------------------------------------

    def nearest_neighbors(self, source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For each source point, its nearest target point (ties: any) and the distance.

        Parameters
        ----------
        source : (s, 3) float
        target : (t, 3) float
            Not empty. An empty target or a non-finite coordinate raises ValueError.

        Returns
        -------
        index : (s,) int32
        distance : (s,) float64
        """
        ...

    def nearest_index(self, target: np.ndarray) -> NearestIndex:
        """The target prepared once for many queries (an ICP's rounds):
        `nearest_index(target).query(source)` is `nearest_neighbors(source, target)`.

        Parameters
        ----------
        target : (t, 3) float

        Returns
        -------
        NearestIndex
        """
        ...

    def cross_covariance(self, source: np.ndarray, target: np.ndarray,
                         weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Weighted centroids of paired points and their cross-covariance
        H = sum_i w_i (s_i - cs)(t_i - ct)^T, what a Kabsch fit takes.

        Parameters
        ----------
        source : (n, 3) float
        target : (n, 3) float
            Paired row by row with source.
        weights : (n,) float, optional
            All ones when None.

        Returns
        -------
        cs : (3,) float64
        ct : (3,) float64
        h : (3, 3) float64
        wsum : float
            Zeros everywhere when wsum <= 0.
        """
        ...

    # --- point-pair-feature votes -------------------------------------------------------

    def ppf_votes(self, model_start: np.ndarray, model_ref: np.ndarray, model_alpha: np.ndarray,
                  model_weight: np.ndarray | None, scene_key: np.ndarray, scene_ref: np.ndarray,
                  scene_alpha: np.ndarray, scene_weight: np.ndarray | None, n_refs: int, n_model: int,
                  alpha_bins: int, bucket_cap: int) -> tuple[np.ndarray, np.ndarray]:
        """Drost's point-pair votes: each scene pair votes for (model point, angle bin) with
        the model pairs of its feature key; per scene reference, the best cell and its total.

        Scene pair s votes with the model pairs j of bucket k = min(scene_key[s], K), i.e.
        model_start[k] <= j < model_start[k + 1] (K = len(model_start) - 2: a key past the
        model's last is an empty bucket). A bucket of found > bucket_cap pairs votes with
        bucket_cap of them, lo + i * found // bucket_cap for i < bucket_cap (lo its first).
        The vote goes to row scene_ref[s], cell model_ref[j] * alpha_bins + bin, where bin =
        floor((model_alpha[j] - scene_alpha[s] + pi) * alpha_bins / 2pi) mod alpha_bins in
        float32 arithmetic, and weighs model_weight[j] * scene_weight[s] (a missing table
        weight counts 1).

        Parameters
        ----------
        model_start : (K + 2,) int
            Non-decreasing, from >= 0 to at most M: the model table's first pair of each key.
        model_ref : (M,) int
            Model point of each model pair, in [0, n_model).
        model_alpha : (M,) float32
            Angle of each model pair about the reference normal, radians in [-pi, pi].
        model_weight : (M,) float or None
            Finite, >= 0; None: every pair weighs 1.
        scene_key : (S,) int
            Feature key of each scene pair, >= 0.
        scene_ref : (S,) int
            Scene reference (row) of each scene pair, in [0, n_refs); need not be sorted.
        scene_alpha : (S,) float32
        scene_weight : (S,) float or None
            Finite, >= 0; None: every pair weighs 1.
        n_refs : int
            Scene references (rows).
        n_model : int
            Model points; a row has n_model * alpha_bins cells.
        alpha_bins : int
        bucket_cap : int
            At least 1.

        Returns
        -------
        best : (n_refs,) int64
            Per row the first cell of the largest total (0 for a row without votes).
        votes : (n_refs,) float64
            That total: an exact count where both tables are unweighted; float64 sums in
            the votes' order from the reference (a device without doubles sums in float32).
        """
        ...

    # --- the mosaic's kernels ----------------------------------------------------------

    def led(self, image: np.ndarray, half: int) -> np.ndarray:
        """Local edge density: the mean of `image` over the (2 half + 1)^2 window centred
        on each pixel, pixels outside counting as 0.

        Parameters
        ----------
        image : (h, w) float
        half : int

        Returns
        -------
        density : (h, w) float
            float64 from the reference, float32 from a device.
        """
        ...

    def block_entropy(self, levels: np.ndarray, block: int, n_levels: int) -> np.ndarray:
        """Quadratic entropy 1 - sum_l P_l^2 of every block x block block of quantised
        levels; a real level v counts 1 - frac(v) in bin floor(v) and frac(v) in the next.

        Parameters
        ----------
        levels : (h, w) float
            In [0, n_levels - 1]; h, w >= block.
        block : int
        n_levels : int
            At most 64.

        Returns
        -------
        entropy : (h - block + 1, w - block + 1) float
            Entry (y, x) is the block whose top-left is (y, x); float64 from the
            reference, float32 from a device.
        """
        ...


@runtime_checkable
class DeviceTiming(Protocol):
    """Optional, for benchmarks: a backend whose kernels run on a device apart from the
    host (Warp on CUDA) can time a kernel alone, its inputs already on the device."""

    def device_kernel(self, family: str, *inputs) -> Callable[[], None] | None:
        """A callable that runs one kernel family on `inputs` uploaded once, and waits for it.

        Parameters
        ----------
        family : str
            "lcs" (inputs: those of `lcs_lengths`) or "nearest" (inputs: source, target
            of `nearest_neighbors`).
        *inputs : np.ndarray and scalars

        Returns
        -------
        run : callable or None
            None where the kernels run on the host (there is no transfer to leave out).
        """
        ...
