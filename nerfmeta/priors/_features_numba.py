"""numba kernel of the learned start's per-point inputs (:func:`nerfmeta.priors.occupancy.occupancy_inputs`; imported
only when numba is installed).

PyTorch's version projects every coarse point into every training view as whole (V, N) arrays, gathers the masks and
colours there and reduces them: about 0.25 s of the 0.4 s the default route spent building a 128 px scene's start
on one core of the 2-core CPU (180k points, 24 views), most of it in writing and reading those arrays. Here each
point visits the views one after another with its counts and colour sums in registers, and writes its ten features
and its hull test once. It runs on one thread over a range of points and releases the GIL.
"""

from __future__ import annotations

import math

import numba
import numpy


@numba.njit(cache=True, nogil=True)
def point_inputs(points, projection, flags, images, misses: int, miss_every: int, features, inside, n0: int,
                 n1: int) -> None:  # pragma: no cover - compiled
    """Features and hull test of the points ``n0 <= n < n1``.

    ``points`` (N, 3); per view ``projection`` (V, 3, 4) float64, the rows giving a point's pixel position times its
    depth and the depth (:func:`nerfmeta.priors.occupancy.projection_matrices`); ``flags`` (V, H, W) uint8, bit 0 the
    foreground mask, bit 1 the mask dilated a pixel, bit 2 dilated
    :data:`~nerfmeta.priors.occupancy.ALLOWED_MARGIN_PX` pixels; ``images`` (V, H, W, 3). A point is seen by a view
    when its depth exceeds 1e-6 and it falls inside the image (as :func:`nerfmeta.priors.carve.lookup`). Writes
    ``features`` (10, N) (:func:`~nerfmeta.priors.occupancy.point_features`' order) and ``inside`` (N,)
    (:func:`~nerfmeta.priors.carve.in_hull` on the masks of bit 2, ``misses`` and ``miss_every`` its rule).
    """
    v, h, w = flags.shape
    for n in range(n0, n1):
        px, py, pz = points[n, 0], points[n, 1], points[n, 2]
        n_seen, n_fg, n_fg1, n_wide = 0, 0, 0, 0
        s0, s1, s2, q0, q1, q2 = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        for k in range(v):
            m = projection[k]
            depth = m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + m[2, 3]
            if not depth > 1e-6:
                continue
            inverse = 1.0 / depth
            x = (m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + m[0, 3]) * inverse
            y = (m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + m[1, 3]) * inverse
            if not (x >= 0.0 and x < w and y >= 0.0 and y < h):  # NaN too: not seen
                continue
            col, row = int(x), int(y)  # x, y >= 0: truncation is the floor
            n_seen += 1
            f = flags[k, row, col]
            n_wide += (f >> 2) & 1
            n_fg1 += (f >> 1) & 1
            if f & 1:
                n_fg += 1
                # in float64: the spread is the root of a difference of squares' sums, float32 squares leave ~1e-4
                pixel = images[k, row, col]
                r, g, b = numpy.float64(pixel[0]), numpy.float64(pixel[1]), numpy.float64(pixel[2])
                s0, s1, s2 = s0 + r, s1 + g, s2 + b
                q0, q1, q2 = q0 + r * r, q1 + g * g, q2 + b * b
        by_seen, by_fg = 1.0 / max(n_seen, 1), 1.0 / max(n_fg, 1)
        m0, m1, m2 = s0 * by_fg, s1 * by_fg, s2 * by_fg
        var = (max(q0 * by_fg - m0 * m0, 0.0) + max(q1 * by_fg - m1 * m1, 0.0) + max(q2 * by_fg - m2 * m2, 0.0)) / 3.0
        background = n_seen - n_fg1
        features[0, n] = n_seen / v
        features[1, n] = n_fg * by_seen
        features[2, n] = n_fg1 * by_seen
        features[3, n] = 1.0 if background == 0 else 0.0
        features[4, n] = 1.0 if background <= 1 else 0.0
        features[5, n], features[6, n], features[7, n] = m0, m1, m2
        features[8, n] = math.sqrt(var)
        features[9, n] = n_fg / v
        inside[n] = n_seen > 0 and n_seen - n_wide <= min(n_seen // miss_every, misses)
