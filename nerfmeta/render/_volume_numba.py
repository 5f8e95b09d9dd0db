"""numba kernels of :func:`nerfmeta.render.volume.render_packed` (imported only when numba is installed).

Samples are packed as there: one flat list, the samples of a ray contiguous and front to back, ``ray`` (M,) the
non-decreasing ray of each. Per ray, the transmittance runs as a product in float64, ``T_0 = 1`` and
``T_{i+1} = T_i exp(-tau_i)``, and the weight is ``w_i = T_i alpha_i = -T_i expm1(-tau_i)``, both factors computed
beforehand in float64 (PyTorch's vectorised ``exp`` and ``expm1``): each to a relative error of a few ulp however
small, so the weights are exact for tiny ``tau`` and behind a nearly opaque sample alike (``T = exp(-40)`` stays
4.2e-18, where ``1 + expm1(-40)`` would round to 0). The backward of ``sum_i g_i w_i + h T_final`` over a ray is, for each sample ``j``,

    d/dtau_j = g_j T_{j+1} - sum_{i > j} g_i w_i - h T_final,

one pass from the ray's back to its front. Each call runs on one thread and releases the GIL.
"""

from __future__ import annotations

import numba


@numba.njit(cache=True, nogil=True)
def weights_forward(em1, decay, ray, t_before, weights, t_final):  # pragma: no cover - compiled
    """From ``em1`` and ``decay`` (M,) float64, ``expm1(-tau)`` and ``exp(-tau)``: ``t_before`` (M,) float64 ``T_i``,
    ``weights`` (M,) ``w_i`` (computed in float64, stored in the array's dtype), and ``t_final`` (n_rays,) float64 for
    every ray with samples (the caller fills it with 1 first)."""
    n = em1.shape[0]
    i = 0
    while i < n:
        r = ray[i]
        t = 1.0
        while i < n and ray[i] == r:
            t_before[i] = t
            weights[i] = -t * em1[i]
            t = t * decay[i]
            i += 1
        t_final[r] = t


@numba.njit(cache=True, nogil=True)
def weights_backward(em1, decay, ray, t_before, t_final, grad_w, grad_t, grad_tau):  # pragma: no cover - compiled
    """``grad_tau`` (M,) from the weights' gradient ``grad_w`` (M,) and the final transmittance's ``grad_t`` (n_rays,),
    summed in float64, stored in the array's dtype."""
    k = em1.shape[0] - 1
    while k >= 0:
        r = ray[k]
        behind = grad_t[r] * t_final[r]  # h T_final + sum of g_i w_i over the samples behind k
        while k >= 0 and ray[k] == r:
            t, e, g = t_before[k], em1[k], grad_w[k]
            grad_tau[k] = g * t * decay[k] - behind
            behind -= g * t * e
            k -= 1


@numba.njit(cache=True, nogil=True)
def composite_forward(weights, colour, sel, ray, t, rgb, depth):  # pragma: no cover - compiled
    """Adds to ``rgb`` (n_rays, 3) the weighted colours (K, 3) of the samples ``sel`` (K,) (empty: every sample,
    K = M) and to ``depth`` (n_rays,) the weighted distances ``t`` (M,) of every sample, summed per run of one ray's
    samples in float64 registers and added once a run (so the sums are right for any order of ``ray``; packed
    samples, a ray's samples contiguous, make one run a ray)."""
    n = weights.shape[0]
    i = 0
    while i < n:
        r, acc = ray[i], 0.0
        while i < n and ray[i] == r:
            acc += weights[i] * t[i]
            i += 1
        depth[r] += acc
    every = sel.shape[0] == 0
    n = colour.shape[0]
    k = 0
    while k < n:
        r = ray[k if every else sel[k]]
        red = green = blue = 0.0
        while k < n:
            i = k if every else sel[k]
            if ray[i] != r:
                break
            w = weights[i]
            red += w * colour[k, 0]
            green += w * colour[k, 1]
            blue += w * colour[k, 2]
            k += 1
        rgb[r, 0] += red
        rgb[r, 1] += green
        rgb[r, 2] += blue


@numba.njit(cache=True, nogil=True)
def composite_backward(weights, colour, sel, ray, t, grad_rgb, grad_depth, grad_w, grad_colour):  # pragma: no cover - compiled
    """The gradients of :func:`composite_forward`'s sums: ``grad_w`` (M,), ``grad_colour`` (K, 3)."""
    for i in range(weights.shape[0]):
        grad_w[i] = t[i] * grad_depth[ray[i]]
    every = sel.shape[0] == 0
    for k in range(colour.shape[0]):
        i = k if every else sel[k]
        r, w = ray[i], weights[i]
        dot = 0.0
        for c in range(3):
            g = grad_rgb[r, c]
            dot += colour[k, c] * g
            grad_colour[k, c] = w * g
        grad_w[i] += dot
