"""Numba kernels of the CPU rasterizer: projection, tile binning, compositing, and their backward.

Everything runs in float64 (scalar CPU code gains little from float32, and float64 keeps the
kernels within 1e-10 of the dense twin, so thresholds such as alpha >= 1/255 decide the same way
in both). ``fastmath`` stays off: it would let LLVM reorder the transmittance products and break
that agreement. Work is split over tiles (compositing) or chunks of Gaussians (projection) with
``prange``; the backward pass writes each (tile, Gaussian) pair's gradient into its own row and
reduces the rows per Gaussian afterwards, so no two threads ever add into the same memory and the
result does not depend on the thread count.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ._common import ALPHA_MAX, ALPHA_MIN, CUTOFF_POWER, LOWPASS, T_MIN, TILE

# Columns of the per-intersection gradient rows written by ``raster_backward``.
G_U, G_V, G_CA, G_CB, G_CC, G_OPA, G_Z, G_COL = 0, 1, 2, 3, 4, 5, 6, 7

_CHUNK = 256  # Gaussians per projection work item


@njit(cache=True, inline="always")
def _rotmat(qw, qx, qy, qz, R):
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    w, x, y, z = qw / n, qx / n, qy / n, qz / n
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - w * z)
    R[0, 2] = 2 * (x * z + w * y)
    R[1, 0] = 2 * (x * y + w * z)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - w * x)
    R[2, 0] = 2 * (x * z - w * y)
    R[2, 1] = 2 * (y * z + w * x)
    R[2, 2] = 1 - 2 * (x * x + y * y)
    return n, w, x, y, z


@njit(cache=True, inline="always")
def _camera_terms(means, g, viewmat, fx, fy, lims, JW, near, far):
    """Camera-space centre and the 2x3 matrix J W; returns (tx, ty, tz, cx_clamped, cy_clamped, ok)."""
    mx, my, mz = means[g, 0], means[g, 1], means[g, 2]
    tx = viewmat[0, 0] * mx + viewmat[0, 1] * my + viewmat[0, 2] * mz + viewmat[0, 3]
    ty = viewmat[1, 0] * mx + viewmat[1, 1] * my + viewmat[1, 2] * mz + viewmat[1, 3]
    tz = viewmat[2, 0] * mx + viewmat[2, 1] * my + viewmat[2, 2] * mz + viewmat[2, 3]
    if not (tz >= near and tz <= far):
        return tx, ty, tz, 0.0, 0.0, False
    rx = min(max(tx / tz, -lims[0]), lims[1])
    ry = min(max(ty / tz, -lims[2]), lims[3])
    xc, yc = tz * rx, tz * ry
    j00, j02 = fx / tz, -fx * xc / (tz * tz)
    j11, j12 = fy / tz, -fy * yc / (tz * tz)
    for k in range(3):
        JW[0, k] = j00 * viewmat[0, k] + j02 * viewmat[2, k]
        JW[1, k] = j11 * viewmat[1, k] + j12 * viewmat[2, k]
    return tx, ty, tz, xc, yc, True


@njit(cache=True, parallel=True)
def project_forward(means, quats, scales, viewmat, intr, lims, width, height, near, far,
                    means2d, depths, conics, rects):
    """EWA projection. Writes means2d [N, 2], depths [N], conics [N, 3] and the pixel rectangle
    rects [N, 4] = (x0, x1, y0, y1) (inclusive) that bounds the 3-sigma ellipse inside the image;
    x0 > x1 marks a Gaussian that is culled (centre outside [near, far] or no pixel covered)."""
    n = means.shape[0]
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    for c in prange((n + _CHUNK - 1) // _CHUNK):
        R = np.empty((3, 3))
        JW = np.empty((2, 3))
        A = np.empty((2, 3))
        for g in range(c * _CHUNK, min(n, (c + 1) * _CHUNK)):
            rects[g, 0], rects[g, 1], rects[g, 2], rects[g, 3] = 0, -1, 0, -1
            tx, ty, tz, xc, yc, ok = _camera_terms(means, g, viewmat, fx, fy, lims, JW, near, far)
            depths[g] = tz
            if not ok:
                means2d[g, 0] = means2d[g, 1] = 0.0
                conics[g, 0] = conics[g, 1] = conics[g, 2] = 0.0
                continue
            _rotmat(quats[g, 0], quats[g, 1], quats[g, 2], quats[g, 3], R)
            # A = J W R S, so that Sigma2d = A A^T (+ low-pass).
            for i in range(2):
                for k in range(3):
                    A[i, k] = (JW[i, 0] * R[0, k] + JW[i, 1] * R[1, k] + JW[i, 2] * R[2, k]) * scales[g, k]
            a = A[0, 0] * A[0, 0] + A[0, 1] * A[0, 1] + A[0, 2] * A[0, 2] + LOWPASS
            b = A[0, 0] * A[1, 0] + A[0, 1] * A[1, 1] + A[0, 2] * A[1, 2]
            cc = A[1, 0] * A[1, 0] + A[1, 1] * A[1, 1] + A[1, 2] * A[1, 2] + LOWPASS
            det = a * cc - b * b
            u = fx * tx / tz + cx
            v = fy * ty / tz + cy
            means2d[g, 0], means2d[g, 1] = u, v
            conics[g, 0], conics[g, 1], conics[g, 2] = cc / det, -b / det, a / det
            if not (det > 0.0):
                continue
            # The 3-sigma ellipse d^T Sigma^-1 d <= 9 spans exactly 3 sqrt(Sigma_xx) in x; the
            # slack keeps the rectangle conservative under rounding.
            ex = 3.0 * math.sqrt(a) * (1 + 1e-9) + 1e-9
            ey = 3.0 * math.sqrt(cc) * (1 + 1e-9) + 1e-9
            x0, x1 = max(0.0, math.ceil(u - ex)), min(width - 1.0, math.floor(u + ex))
            y0, y1 = max(0.0, math.ceil(v - ey)), min(height - 1.0, math.floor(v + ey))
            if x0 <= x1 and y0 <= y1:
                rects[g, 0], rects[g, 1], rects[g, 2], rects[g, 3] = int(x0), int(x1), int(y0), int(y1)


@njit(cache=True)
def bin_tiles(rects, depths, width, height):
    """Tile lists in depth order: returns (offsets [n_tiles + 1], gauss_ids [n_isect]).

    One global stable sort by depth, then Gaussians are appended to their tiles in that order, so
    every tile's list is already sorted front to back (ties broken by index, like the twin)."""
    ntx = (width + TILE - 1) // TILE
    nty = (height + TILE - 1) // TILE
    n = rects.shape[0]
    counts = np.zeros(ntx * nty + 1, dtype=np.int64)
    for g in range(n):
        if rects[g, 0] > rects[g, 1]:
            continue
        for ty in range(rects[g, 2] // TILE, rects[g, 3] // TILE + 1):
            for tx in range(rects[g, 0] // TILE, rects[g, 1] // TILE + 1):
                counts[ty * ntx + tx + 1] += 1
    offsets = np.cumsum(counts)
    cursor = offsets[:-1].copy()
    ids = np.empty(offsets[-1], dtype=np.int64)
    order = np.argsort(depths, kind="mergesort")
    for i in range(n):
        g = order[i]
        if rects[g, 0] > rects[g, 1]:
            continue
        for ty in range(rects[g, 2] // TILE, rects[g, 3] // TILE + 1):
            for tx in range(rects[g, 0] // TILE, rects[g, 1] // TILE + 1):
                t = ty * ntx + tx
                ids[cursor[t]] = g
                cursor[t] += 1
    return offsets, ids


@njit(cache=True, parallel=True)
def raster_forward(offsets, ids, rects, means2d, conics, opacities, colors, depths, background,
                   width, height, out_rgb, out_depth, out_T, out_count):
    """Front-to-back compositing per 16x16 tile.

    Loops run Gaussian-outer, pixel-inner over the part of the tile that the Gaussian's 3-sigma
    rectangle covers, which skips most (pixel, Gaussian) pairs of a tile list. Writes
    out_rgb [H, W, D], out_depth [H, W], out_T [H, W] (final transmittance) and out_count [H, W]
    (1 + position in the tile list of the last splat composited, 0 if none)."""
    ntx = (width + TILE - 1) // TILE
    nty = (height + TILE - 1) // TILE
    nd = colors.shape[1]
    for t in prange(ntx * nty):
        tx0 = (t % ntx) * TILE
        ty0 = (t // ntx) * TILE
        tx1 = min(tx0 + TILE, width) - 1
        ty1 = min(ty0 + TILE, height) - 1
        tw = tx1 - tx0 + 1
        npix = tw * (ty1 - ty0 + 1)
        T = np.ones(npix)
        acc = np.zeros((npix, nd))
        accd = np.zeros(npix)
        count = np.zeros(npix, dtype=np.int32)
        done = np.zeros(npix, dtype=np.bool_)
        ndone = 0
        start = offsets[t]
        for k in range(start, offsets[t + 1]):
            g = ids[k]
            mu, mv = means2d[g, 0], means2d[g, 1]
            ca, cb, cc = conics[g, 0], conics[g, 1], conics[g, 2]
            op = opacities[g]
            for py in range(max(ty0, rects[g, 2]), min(ty1, rects[g, 3]) + 1):
                dy = mv - py
                for px in range(max(tx0, rects[g, 0]), min(tx1, rects[g, 1]) + 1):
                    p = (py - ty0) * tw + (px - tx0)
                    if done[p]:
                        continue
                    dx = mu - px
                    power = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    if power > CUTOFF_POWER:
                        continue
                    alpha = min(ALPHA_MAX, op * math.exp(-power))
                    if alpha < ALPHA_MIN:
                        continue
                    test_T = T[p] * (1.0 - alpha)
                    if test_T < T_MIN:
                        done[p] = True
                        ndone += 1
                        continue
                    wgt = alpha * T[p]
                    for ch in range(nd):
                        acc[p, ch] += wgt * colors[g, ch]
                    accd[p] += wgt * depths[g]
                    T[p] = test_T
                    count[p] = k - start + 1
            if ndone == npix:
                break
        for py in range(ty0, ty1 + 1):
            for px in range(tx0, tx1 + 1):
                p = (py - ty0) * tw + (px - tx0)
                for ch in range(nd):
                    out_rgb[py, px, ch] = acc[p, ch] + T[p] * background[ch]
                out_depth[py, px] = accd[p]
                out_T[py, px] = T[p]
                out_count[py, px] = count[p]


@njit(cache=True, parallel=True)
def raster_backward(offsets, ids, rects, means2d, conics, opacities, colors, depths, background,
                    width, height, out_T, out_count, g_rgb, g_alpha, g_depth, g_isect):
    """The 3DGS backward pass: each pixel's list walked back to front, transmittance recovered by
    division (alpha <= 0.99 keeps it exact enough), colour behind each splat accumulated.

    g_rgb [H, W, D], g_alpha [H, W], g_depth [H, W] are dL/d(outputs). Row k of g_isect
    [n_isect, 7 + D] receives dL/d(u, v, conic a, b, c, opacity, z, colour) of the pair ids[k]."""
    ntx = (width + TILE - 1) // TILE
    nty = (height + TILE - 1) // TILE
    nd = colors.shape[1]
    for t in prange(ntx * nty):
        tx0 = (t % ntx) * TILE
        ty0 = (t // ntx) * TILE
        tx1 = min(tx0 + TILE, width) - 1
        ty1 = min(ty0 + TILE, height) - 1
        tw = tx1 - tx0 + 1
        npix = tw * (ty1 - ty0 + 1)
        start = offsets[t]
        T = np.empty(npix)
        Tf = np.empty(npix)
        count = np.empty(npix, dtype=np.int32)
        gC = np.empty((npix, nd))
        gD = np.empty(npix)
        gbg = np.empty(npix)  # dL/dalpha_i pieces that involve only the final T: background and alpha
        behind = np.zeros((npix, nd))
        behind_d = np.zeros(npix)
        last_a = np.zeros(npix)
        last_c = np.zeros((npix, nd))
        last_d = np.zeros(npix)
        maxc = 0
        for py in range(ty0, ty1 + 1):
            for px in range(tx0, tx1 + 1):
                p = (py - ty0) * tw + (px - tx0)
                T[p] = Tf[p] = out_T[py, px]
                count[p] = out_count[py, px]
                maxc = max(maxc, count[p])
                s = 0.0
                for ch in range(nd):
                    gC[p, ch] = g_rgb[py, px, ch]
                    s += background[ch] * g_rgb[py, px, ch]
                gD[p] = g_depth[py, px]
                # C has + T_final * bg and alpha = 1 - T_final; d T_final / d alpha_i = -T_final / (1 - alpha_i)
                gbg[p] = Tf[p] * (g_alpha[py, px] - s)
        for k in range(start + maxc - 1, start - 1, -1):
            g = ids[k]
            mu, mv = means2d[g, 0], means2d[g, 1]
            ca, cb, cc = conics[g, 0], conics[g, 1], conics[g, 2]
            op = opacities[g]
            z = depths[g]
            gu = gv = gca = gcb = gcc = gop = gz = 0.0
            for ch in range(nd):
                g_isect[k, G_COL + ch] = 0.0
            kk = k - start
            for py in range(max(ty0, rects[g, 2]), min(ty1, rects[g, 3]) + 1):
                dy = mv - py
                for px in range(max(tx0, rects[g, 0]), min(tx1, rects[g, 1]) + 1):
                    p = (py - ty0) * tw + (px - tx0)
                    if kk >= count[p]:
                        continue
                    dx = mu - px
                    power = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    if power > CUTOFF_POWER:
                        continue
                    G = math.exp(-power)
                    raw = op * G
                    alpha = min(ALPHA_MAX, raw)
                    if alpha < ALPHA_MIN:
                        continue
                    T[p] = T[p] / (1.0 - alpha)
                    wgt = alpha * T[p]
                    dl_da = 0.0
                    for ch in range(nd):
                        g_isect[k, G_COL + ch] += wgt * gC[p, ch]
                        behind[p, ch] = last_a[p] * last_c[p, ch] + (1.0 - last_a[p]) * behind[p, ch]
                        dl_da += (colors[g, ch] - behind[p, ch]) * gC[p, ch]
                        last_c[p, ch] = colors[g, ch]
                    gz += wgt * gD[p]
                    behind_d[p] = last_a[p] * last_d[p] + (1.0 - last_a[p]) * behind_d[p]
                    dl_da += (z - behind_d[p]) * gD[p]
                    dl_da = dl_da * T[p] + gbg[p] / (1.0 - alpha)
                    last_a[p] = alpha
                    last_d[p] = z
                    if raw < ALPHA_MAX:  # the clamp passes no gradient
                        gop += G * dl_da
                        dl_dpow = -op * G * dl_da
                        gu += dl_dpow * (ca * dx + cb * dy)
                        gv += dl_dpow * (cb * dx + cc * dy)
                        gca += 0.5 * dx * dx * dl_dpow
                        gcb += dx * dy * dl_dpow
                        gcc += 0.5 * dy * dy * dl_dpow
            g_isect[k, G_U] = gu
            g_isect[k, G_V] = gv
            g_isect[k, G_CA] = gca
            g_isect[k, G_CB] = gcb
            g_isect[k, G_CC] = gcc
            g_isect[k, G_OPA] = gop
            g_isect[k, G_Z] = gz
        # Rows past the longest pixel list of this tile were never reached: zero them.
        for k in range(start + maxc, offsets[t + 1]):
            for j in range(g_isect.shape[1]):
                g_isect[k, j] = 0.0


@njit(cache=True)
def reduce_isect(ids, g_isect, n):
    """Sum the per-intersection rows [n_isect, 7 + D] into per-Gaussian rows [n, 7 + D]."""
    out = np.zeros((n, g_isect.shape[1]))
    for k in range(ids.shape[0]):
        g = ids[k]
        for j in range(g_isect.shape[1]):
            out[g, j] += g_isect[k, j]
    return out


@njit(cache=True, parallel=True)
def project_backward(means, quats, scales, viewmat, intr, lims, near, far, conics, rects, g_proj,
                     g_means, g_quats, g_scales):
    """Chain rule through ``project_forward`` for every Gaussian that was drawn.

    g_proj [N, 7+D] holds dL/d(u, v, conic a, b, c, ., z, ...) per Gaussian. Writes g_means [N, 3],
    g_quats [N, 4] (w.r.t. the unnormalised input) and g_scales [N, 3]."""
    n = means.shape[0]
    fx, fy = intr[0], intr[1]
    for c in prange((n + _CHUNK - 1) // _CHUNK):
        R = np.empty((3, 3))
        JW = np.empty((2, 3))
        WM = np.empty((3, 3))  # W R S
        A = np.empty((2, 3))
        gA = np.empty((2, 3))
        gM = np.empty((3, 3))
        gR = np.empty((3, 3))
        for g in range(c * _CHUNK, min(n, (c + 1) * _CHUNK)):
            for k in range(3):
                g_means[g, k] = 0.0
                g_scales[g, k] = 0.0
            for k in range(4):
                g_quats[g, k] = 0.0
            if rects[g, 0] > rects[g, 1]:
                continue
            tx, ty, tz, xc, yc, ok = _camera_terms(means, g, viewmat, fx, fy, lims, JW, near, far)
            qn, w, x, y, z = _rotmat(quats[g, 0], quats[g, 1], quats[g, 2], quats[g, 3], R)
            for i in range(3):
                for k in range(3):
                    WM[i, k] = (viewmat[i, 0] * R[0, k] + viewmat[i, 1] * R[1, k] + viewmat[i, 2] * R[2, k]) * scales[g, k]
            j00, j02 = fx / tz, -fx * xc / (tz * tz)
            j11, j12 = fy / tz, -fy * yc / (tz * tz)
            for k in range(3):  # A = J (W R S)
                A[0, k] = j00 * WM[0, k] + j02 * WM[2, k]
                A[1, k] = j11 * WM[1, k] + j12 * WM[2, k]
            # conic Q = Sigma^-1 with power = 0.5 a dx^2 + b dx dy + 0.5 c dy^2: the off-diagonal
            # b appears twice in Q, so dL/dQ = [[ga, gb/2], [gb/2, gc]]; dL/dSigma = -Q dL/dQ Q.
            qa, qb, qc = conics[g, 0], conics[g, 1], conics[g, 2]
            ga, gb, gc = g_proj[g, G_CA], 0.5 * g_proj[g, G_CB], g_proj[g, G_CC]
            m00 = ga * qa + gb * qb
            m01 = ga * qb + gb * qc
            m10 = gb * qa + gc * qb
            m11 = gb * qb + gc * qc
            s00 = -(qa * m00 + qb * m10)
            s01 = -(qa * m01 + qb * m11)
            s11 = -(qb * m01 + qc * m11)
            # Sigma = A A^T: dL/dA = 2 S A with S = dL/dSigma symmetric.
            for k in range(3):
                gA[0, k] = 2.0 * (s00 * A[0, k] + s01 * A[1, k])
                gA[1, k] = 2.0 * (s01 * A[0, k] + s11 * A[1, k])
            # A = J (W R S): dL/dJ = dL/dA (W R S)^T ; dL/d(W R S) = J^T dL/dA
            gj00 = gA[0, 0] * WM[0, 0] + gA[0, 1] * WM[0, 1] + gA[0, 2] * WM[0, 2]
            gj02 = gA[0, 0] * WM[2, 0] + gA[0, 1] * WM[2, 1] + gA[0, 2] * WM[2, 2]
            gj11 = gA[1, 0] * WM[1, 0] + gA[1, 1] * WM[1, 1] + gA[1, 2] * WM[1, 2]
            gj12 = gA[1, 0] * WM[2, 0] + gA[1, 1] * WM[2, 1] + gA[1, 2] * WM[2, 2]
            # gWM[i, k] = sum_r J[r, i] gA[r, k]; then gM = W^T gWM (M = R S), gR = gM S.
            for k in range(3):
                gw0 = j00 * gA[0, k]
                gw1 = j11 * gA[1, k]
                gw2 = j02 * gA[0, k] + j12 * gA[1, k]
                for i in range(3):
                    gM[i, k] = viewmat[0, i] * gw0 + viewmat[1, i] * gw1 + viewmat[2, i] * gw2
            for k in range(3):
                s = 0.0
                for i in range(3):
                    gR[i, k] = gM[i, k] * scales[g, k]
                    s += gM[i, k] * R[i, k]
                g_scales[g, k] = s
            # Jacobian entries depend on t through tz and the clamped xc = tz * clamp(tx / tz).
            rx = tx / tz
            if rx < -lims[0] or rx > lims[1]:
                dxc_dtx, dxc_dtz = 0.0, xc / tz
            else:
                dxc_dtx, dxc_dtz = 1.0, 0.0
            ry = ty / tz
            if ry < -lims[2] or ry > lims[3]:
                dyc_dty, dyc_dtz = 0.0, yc / tz
            else:
                dyc_dty, dyc_dtz = 1.0, 0.0
            tz2 = tz * tz
            tz3 = tz2 * tz
            gu, gv = g_proj[g, G_U], g_proj[g, G_V]
            gtx = gu * fx / tz - gj02 * fx * dxc_dtx / tz2
            gty = gv * fy / tz - gj12 * fy * dyc_dty / tz2
            gtz = (
                g_proj[g, G_Z]
                - gu * fx * tx / tz2
                - gv * fy * ty / tz2
                - gj00 * fx / tz2
                - gj11 * fy / tz2
                + gj02 * (-fx * dxc_dtz / tz2 + 2.0 * fx * xc / tz3)
                + gj12 * (-fy * dyc_dtz / tz2 + 2.0 * fy * yc / tz3)
            )
            for k in range(3):
                g_means[g, k] = viewmat[0, k] * gtx + viewmat[1, k] * gty + viewmat[2, k] * gtz
            # R(q / |q|): derivative of each entry w.r.t. the unit quaternion, then projection onto
            # the tangent of the normalisation.
            gw = 2 * (-z * gR[0, 1] + y * gR[0, 2] + z * gR[1, 0] - x * gR[1, 2] - y * gR[2, 0] + x * gR[2, 1])
            gx = 2 * (y * gR[0, 1] + z * gR[0, 2] + y * gR[1, 0] - 2 * x * gR[1, 1] - w * gR[1, 2]
                      + z * gR[2, 0] + w * gR[2, 1] - 2 * x * gR[2, 2])
            gy = 2 * (-2 * y * gR[0, 0] + x * gR[0, 1] + w * gR[0, 2] + x * gR[1, 0] + z * gR[1, 2]
                      - w * gR[2, 0] + z * gR[2, 1] - 2 * y * gR[2, 2])
            gz = 2 * (-2 * z * gR[0, 0] - w * gR[0, 1] + x * gR[0, 2] + w * gR[1, 0] - 2 * z * gR[1, 1]
                      + y * gR[1, 2] + x * gR[2, 0] + y * gR[2, 1])
            dot = w * gw + x * gx + y * gy + z * gz
            g_quats[g, 0] = (gw - w * dot) / qn
            g_quats[g, 1] = (gx - x * dot) / qn
            g_quats[g, 2] = (gy - y * dot) / qn
            g_quats[g, 3] = (gz - z * dot) / qn
