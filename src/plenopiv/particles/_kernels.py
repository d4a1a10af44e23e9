"""numba kernels behind :mod:`plenopiv.particles.peaks` (private; arrays and scalars only).

Volumes are indexed ``[z, y, x]``; peaks are ``(N, 3)`` integer voxel indices in that order.
Each kernel ``name`` has its plain-NumPy twin ``name_numpy`` here, with the same arguments and
outputs; the tests compare the two.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def suppress_close(peaks, shape, separation):
    """Greedy non-maximum suppression of peaks closer than ``separation`` (per axis).

    ``peaks`` (N, 3) int64 must be sorted by decreasing peak value. A peak is dropped when an
    already kept peak lies inside the ellipsoid ``sum_a (d_a / separation_a)**2 < 1`` around
    it. Returns a boolean mask of the peaks kept.
    """
    n = peaks.shape[0]
    keep = np.zeros(n, np.bool_)
    taken = np.zeros((shape[0], shape[1], shape[2]), np.bool_)
    rz = int(math.ceil(separation[0])) - 1
    ry = int(math.ceil(separation[1])) - 1
    rx = int(math.ceil(separation[2])) - 1
    for k in range(n):
        z, y, x = peaks[k, 0], peaks[k, 1], peaks[k, 2]
        close = False
        for dz in range(-rz, rz + 1):
            zz = z + dz
            if zz < 0 or zz >= shape[0]:
                continue
            for dy in range(-ry, ry + 1):
                yy = y + dy
                if yy < 0 or yy >= shape[1]:
                    continue
                for dx in range(-rx, rx + 1):
                    xx = x + dx
                    if xx < 0 or xx >= shape[2]:
                        continue
                    if not taken[zz, yy, xx]:
                        continue
                    r2 = ((dz / separation[0]) ** 2 + (dy / separation[1]) ** 2
                          + (dx / separation[2]) ** 2)
                    if r2 < 1.0:
                        close = True
                        break
                if close:
                    break
            if close:
                break
        if not close:
            keep[k] = True
            taken[z, y, x] = True
    return keep


@numba.njit(cache=True)
def refine_peaks(volume, peaks, half_box, spacing, gaussian, position, size, intensity):
    """Sub-voxel position, size and integrated intensity of each peak.

    The box around peak ``(z, y, x)`` spans ``+-half_box`` voxels per axis, clipped at the
    volume's edges. ``intensity[n]`` is the sum of the volume over the box.

    If ``gaussian``: per axis a, the 3-point Gaussian through the peak value I0 and the
    samples I-, I+ at ``-+m`` voxels (``m = spacing[a]``) gives
    ``offset = m (ln I- - ln I+) / (2 (ln I- - 2 ln I0 + ln I+))`` and
    ``sigma**2 = -m**2 / (ln I- - 2 ln I0 + ln I+)``; where a sample is <= 0 or the curvature
    is not negative, the 3-point centroid ``m (I+ - I-) / (I- + I0 + I+)`` and the 3-point
    second moment are used instead. Where a sample falls outside the volume the offset is 0
    and sigma NaN.
    Otherwise: the intensity-weighted centroid and second central moment over the box.
    """
    nz, ny, nx = volume.shape
    for n in range(peaks.shape[0]):
        z, y, x = peaks[n, 0], peaks[n, 1], peaks[n, 2]
        z0 = max(z - half_box[0], 0)
        z1 = min(z + half_box[0] + 1, nz)
        y0 = max(y - half_box[1], 0)
        y1 = min(y + half_box[1] + 1, ny)
        x0 = max(x - half_box[2], 0)
        x1 = min(x + half_box[2] + 1, nx)
        s0 = 0.0
        sz = 0.0
        sy = 0.0
        sx = 0.0
        szz = 0.0
        syy = 0.0
        sxx = 0.0
        for zz in range(z0, z1):
            for yy in range(y0, y1):
                for xx in range(x0, x1):
                    v = np.float64(volume[zz, yy, xx])
                    dz = zz - z
                    dy = yy - y
                    dx = xx - x
                    s0 += v
                    sz += v * dz
                    sy += v * dy
                    sx += v * dx
                    szz += v * dz * dz
                    syy += v * dy * dy
                    sxx += v * dx * dx
        intensity[n] = s0
        if not gaussian:
            if s0 > 0.0:
                cz, cy, cx = sz / s0, sy / s0, sx / s0
                position[n, 0] = z + cz
                position[n, 1] = y + cy
                position[n, 2] = x + cx
                size[n, 0] = math.sqrt(max(szz / s0 - cz * cz, 0.0))
                size[n, 1] = math.sqrt(max(syy / s0 - cy * cy, 0.0))
                size[n, 2] = math.sqrt(max(sxx / s0 - cx * cx, 0.0))
            else:
                position[n, 0] = z
                position[n, 1] = y
                position[n, 2] = x
                size[n, 0] = np.nan
                size[n, 1] = np.nan
                size[n, 2] = np.nan
            continue
        centre = np.float64(volume[z, y, x])
        for a in range(3):
            idx = peaks[n, a]
            m = spacing[a]
            limit = nz if a == 0 else (ny if a == 1 else nx)
            if idx - m < 0 or idx + m > limit - 1:
                position[n, a] = idx
                size[n, a] = np.nan
                continue
            if a == 0:
                lo = np.float64(volume[z - m, y, x])
                hi = np.float64(volume[z + m, y, x])
            elif a == 1:
                lo = np.float64(volume[z, y - m, x])
                hi = np.float64(volume[z, y + m, x])
            else:
                lo = np.float64(volume[z, y, x - m])
                hi = np.float64(volume[z, y, x + m])
            curvature = 0.0
            llo = 0.0
            lhi = 0.0
            if lo > 0.0 and hi > 0.0 and centre > 0.0:
                llo = math.log(lo)
                lhi = math.log(hi)
                curvature = llo - 2.0 * math.log(centre) + lhi
            if curvature < 0.0:
                position[n, a] = idx + m * (llo - lhi) / (2.0 * curvature)
                size[n, a] = m * math.sqrt(-1.0 / curvature)
            else:
                total = lo + centre + hi
                if total > 0.0:
                    c = (hi - lo) / total
                    position[n, a] = idx + m * c
                    size[n, a] = m * math.sqrt(max((lo + hi) / total - c * c, 0.0))
                else:
                    position[n, a] = idx
                    size[n, a] = np.nan


def suppress_close_numpy(peaks, shape, separation):
    """NumPy twin of :func:`suppress_close`, by brute force (``shape`` is not needed)."""
    kept = []
    for p in peaks:
        if all(np.sum(((p - q) / separation) ** 2) >= 1 for q in kept):
            kept.append(p)
    return np.array([any(np.array_equal(p, q) for q in kept) for p in peaks], dtype=bool)


def refine_peaks_numpy(volume, peaks, half_box, spacing, gaussian, position, size, intensity):
    """NumPy twin of :func:`refine_peaks`: the same outputs, written into the same arrays."""
    vol = volume.astype(np.float64)
    for i, p in enumerate(peaks):
        lo = np.maximum(p - half_box, 0)
        hi = np.minimum(p + half_box + 1, vol.shape)
        box = vol[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        intensity[i] = box.sum()
        if not gaussian:
            offsets = [np.arange(lo[a], hi[a]) - p[a] for a in range(3)]
            total = box.sum()
            if total <= 0:
                position[i], size[i] = p, np.nan
                continue
            for a in range(3):
                profile = box.sum(axis=tuple(b for b in range(3) if b != a))
                c = profile @ offsets[a] / total
                position[i, a] = p[a] + c
                size[i, a] = math.sqrt(max(profile @ offsets[a] ** 2 / total - c * c, 0.0))
            continue
        for a in range(3):
            m = spacing[a]
            if p[a] - m < 0 or p[a] + m > vol.shape[a] - 1:
                position[i, a], size[i, a] = p[a], np.nan
                continue
            step = np.zeros(3, int)
            step[a] = m
            i0, im, ip = vol[tuple(p)], vol[tuple(p - step)], vol[tuple(p + step)]
            if min(i0, im, ip) > 0 and np.log(im) - 2 * np.log(i0) + np.log(ip) < 0:
                d = np.log(im) - 2 * np.log(i0) + np.log(ip)
                position[i, a] = p[a] + m * (np.log(im) - np.log(ip)) / (2 * d)
                size[i, a] = m * math.sqrt(-1 / d)
            elif im + i0 + ip > 0:
                c = (ip - im) / (im + i0 + ip)
                position[i, a] = p[a] + m * c
                size[i, a] = m * math.sqrt(max((im + ip) / (im + i0 + ip) - c * c, 0.0))
            else:
                position[i, a], size[i, a] = p[a], np.nan
