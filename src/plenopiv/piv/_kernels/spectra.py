"""Kernels that cut windows out of a volume and form their cross spectrum.

``extract_windows`` copies interrogation windows at arbitrary start voxels out of a volume
(zero outside it). ``cross_spectrum`` takes the real-FFT spectra ``A, B`` of ``p * q`` windows,
laid out ``(kz, p, ky, q, kx)`` as the staged transform of :mod:`plenopiv.piv` leaves them
(``nx`` the real window length along x), and writes the cross spectrum ``conj(A) B`` without
its mean (DC) term into ``out`` shaped ``(p, q, kz, ky, kx)``; per window (Parseval) it returns
the energies about the mean, ``sum((a - mean(a))**2)``, ``sum((b - mean(b))**2)``, and the
total energies ``sum(a**2)``, ``sum(b**2)``, as the columns of an (n, 4) array.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, parallel=True)
def extract_windows(volume, starts, wz, wy, wx):
    n = starts.shape[0]
    nz, ny, nx = volume.shape
    out = np.zeros((n, wz, wy, wx), dtype=np.float32)
    for k in numba.prange(n):
        z0 = starts[k, 0]
        y0 = starts[k, 1]
        x0 = starts[k, 2]
        xa = max(0, -x0)
        xb = min(wx, nx - x0)
        if xb <= xa:
            continue
        for i in range(max(0, -z0), min(wz, nz - z0)):
            for j in range(max(0, -y0), min(wy, ny - y0)):
                out[k, i, j, xa:xb] = volume[z0 + i, y0 + j, x0 + xa : x0 + xb]
    return out


def extract_windows_numpy(volume, starts, wz, wy, wx):
    starts = np.asarray(starts, dtype=np.int64)
    shape = np.array(volume.shape)
    if starts.shape[0] == 0:
        return np.empty((0, wz, wy, wx), np.float32)
    window = np.array([wz, wy, wx])
    pad_lo = np.maximum(0, -starts.min(axis=0))
    pad_hi = np.maximum(0, (starts + window).max(axis=0) - shape)
    padded = np.pad(volume, list(zip(pad_lo, pad_hi, strict=True)), mode="constant")
    s = starts + pad_lo
    iz = s[:, 0, None, None, None] + np.arange(wz)[None, :, None, None]
    iy = s[:, 1, None, None, None] + np.arange(wy)[None, None, :, None]
    ix = s[:, 2, None, None, None] + np.arange(wx)[None, None, None, :]
    return padded[iz, iy, ix].astype(np.float32)


# --------------------------------------------------------------------------------------------
# cross_spectrum
# --------------------------------------------------------------------------------------------


@numba.njit(cache=True)
def cross_spectrum(fa, fb, nx, out):
    kz, p, ky, q, kx = fa.shape
    size = kz * ky * nx
    # loops follow the memory order of the inputs. Serial: a memory-bound pass, short beside
    # its FFT, which a parallel loop speeds up little and compiles much longer
    partial = np.zeros((kz, p * q, 2), dtype=np.float64)
    for i in range(kz):
        for u in range(p):
            for j in range(ky):
                for v in range(q):
                    k = u * q + v
                    sa = 0.0
                    sb = 0.0
                    for m in range(kx):
                        a = fa[i, u, j, v, m]
                        b = fb[i, u, j, v, m]
                        weight = 1.0 if (m == 0 or 2 * m == nx) else 2.0
                        sa += weight * (a.real * a.real + a.imag * a.imag)
                        sb += weight * (b.real * b.real + b.imag * b.imag)
                        out[u, v, i, j, m] = a.conjugate() * b
                    partial[i, k, 0] += sa
                    partial[i, k, 1] += sb
    energy = np.empty((p * q, 4), dtype=np.float64)
    for u in range(p):
        for v in range(q):
            k = u * q + v
            a0 = fa[0, u, 0, v, 0]
            b0 = fb[0, u, 0, v, 0]
            sa = 0.0
            sb = 0.0
            for i in range(kz):
                sa += partial[i, k, 0]
                sb += partial[i, k, 1]
            energy[k, 0] = (sa - (a0.real * a0.real + a0.imag * a0.imag)) / size
            energy[k, 1] = (sb - (b0.real * b0.real + b0.imag * b0.imag)) / size
            energy[k, 2] = sa / size
            energy[k, 3] = sb / size
            out[u, v, 0, 0, 0] = 0.0
    return energy


def cross_spectrum_numpy(fa, fb, nx, out):
    kz, p, ky, q, kx = fa.shape
    fa = fa.transpose(1, 3, 0, 2, 4).astype(np.complex128)
    fb = fb.transpose(1, 3, 0, 2, 4).astype(np.complex128)
    weight = np.full(kx, 2.0)
    weight[0] = 1.0
    if nx % 2 == 0:
        weight[-1] = 1.0
    power_a = (np.abs(fa) ** 2).reshape(p * q, kz, ky, kx)
    power_b = (np.abs(fb) ** 2).reshape(p * q, kz, ky, kx)
    size = kz * ky * nx
    total_a = (power_a * weight).sum(axis=(1, 2, 3)) / size
    total_b = (power_b * weight).sum(axis=(1, 2, 3)) / size
    energy = np.stack(
        [
            total_a - power_a[:, 0, 0, 0] / size,
            total_b - power_b[:, 0, 0, 0] / size,
            total_a,
            total_b,
        ],
        axis=1,
    )
    out[...] = np.conj(fa) * fb
    out[:, :, 0, 0, 0] = 0.0
    return energy
