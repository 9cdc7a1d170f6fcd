"""Warp kernels of the image mosaic (paper sections 3.3.2 and 3.4).

The float64 specification is `relicgpu.backends.numpy` (`led`, `block_entropy`);
`WarpBackend.led` and `WarpBackend.block_entropy` launch these.

- LED (Eq. 4): a (2A+1)^2 box mean with zeros outside the image, done as two
  separable passes (rows, then columns) so a pixel costs O(A), not O(A^2).
  Sums of a binary edge map are integers, exact in float32.
- Block entropy (Eq. 8): for every block top-left (y, x) of a b x b block, the
  quadratic entropy 1 - sum_l P(l)^2 of its gray levels, from a per-thread
  histogram of at most MAX_LEVELS bins. Levels are real numbers in [0, L-1]; a
  level v adds 1 - frac(v) to bin floor(v) and frac(v) to the next (integer
  levels give the plain histogram).
"""
from __future__ import annotations

import warp as wp

MAX_LEVELS = 64
_counts_t = wp.types.vector(length=MAX_LEVELS, dtype=wp.float32)


@wp.kernel
def led_rows(src: wp.array2d(dtype=wp.float32), half: int, out: wp.array2d(dtype=wp.float32)):
    y, x = wp.tid()
    width = src.shape[1]
    lo = wp.max(x - half, 0)
    hi = wp.min(x + half, width - 1)
    s = float(0.0)
    for c in range(lo, hi + 1):
        s += src[y, c]
    out[y, x] = s


@wp.kernel
def led_cols(rows: wp.array2d(dtype=wp.float32), half: int, scale: float, out: wp.array2d(dtype=wp.float32)):
    y, x = wp.tid()
    height = rows.shape[0]
    lo = wp.max(y - half, 0)
    hi = wp.min(y + half, height - 1)
    s = float(0.0)
    for r in range(lo, hi + 1):
        s += rows[r, x]
    out[y, x] = s * scale


@wp.kernel
def block_entropy(levels: wp.array2d(dtype=wp.float32), block: int, n_levels: int, out: wp.array2d(dtype=wp.float32)):
    y, x = wp.tid()
    counts = _counts_t()
    for dy in range(block):
        for dx in range(block):
            v = levels[y + dy, x + dx]
            lo = wp.min(int(wp.floor(v)), n_levels - 1)
            f = v - float(lo)
            counts[lo] = counts[lo] + (1.0 - f)
            if f > 0.0:
                counts[lo + 1] = counts[lo + 1] + f
    s = float(0.0)
    for lv in range(n_levels):
        s += counts[lv] * counts[lv]
    n = float(block * block)
    out[y, x] = 1.0 - s / (n * n)
