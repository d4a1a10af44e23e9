"""Numba kernels of the ray tracer. Arrays and scalars only; see :mod:`.tracer` for the API.

The camera enters as one float64 vector ``g`` whose slots are named by the ``G_*`` constants
below (built by :func:`plenopiv.synthetic.tracer.geometry_vector`). Per ray, in image space
(z towards the sensor, metres): exact vector Snell refraction into the substrate, the lenslet
hit on the lenslet plane, the back side ("physical": refraction into air, then an ideal thin
lenslet; "thesis": the thin lenslet on the in-glass direction, thesis Appendix B),
propagation over f̄ and a bilinear or whole-pixel splat on the sensor. The kernels the tests
check have a plain-NumPy twin here, ``<kernel>_numpy`` (same arguments and outputs,
vectorised over rays).

See docs/methods.md#synthetic-images.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

# ---- slots of the geometry vector ----------------------------------------------------------
G_L3 = 0          # z of the substrate front (= z_mla without a substrate), m
G_T = 1           # substrate thickness, m
G_N = 2           # substrate index
G_ZMLA = 3        # z of the lenslet plane, m
G_FL = 4          # lenslet focal length, m
G_FBAR = 5        # lenslet plane to sensor, m
G_THESIS = 6      # 1.0: "thesis" back side, 0.0: "physical"
G_PITCH = 7       # lenslet pitch, m
G_ROWSP = 8       # lenslet row spacing, m
G_ROWS = 9        # lenslet rows
G_COLS = 10       # lenslet cols
G_HEX = 11        # 1.0 hexagonal grid
G_HEXSHIFT = 12   # mean odd-row shift (pitches) removed to centre a hexagonal grid
G_OFFS = 13       # MLA offset s_o, m
G_OFFT = 14       # MLA offset t_o, m
G_COSG = 15       # cos γ
G_SING = 16       # sin γ
G_PIX = 17        # pixel pitch, m
G_NROWS = 18      # sensor rows
G_NCOLS = 19      # sensor cols
G_FM = 20         # main-lens focal length, m
G_E = 21          # exit pupil offset, m
G_RPUPIL = 22     # pupil radius, m
G_ZINT = 23       # z of the external interface (-l2), m
G_NEXT = 24       # n1/n2 of the external interface (1: none)
G_HASEXT = 25     # 1.0: an external interface is present
G_SPLAT = 26      # 0.0: bilinear splat, 1.0: whole ray into its pixel
G_SHIFTR = 27     # sensor shift: the image content moves by this many pixels along rows
G_SHIFTC = 28     # ... and along cols
G_SIZE = 29

@njit(cache=True, inline="always", error_model="numpy", fastmath=True)
def _round(x):
    return math.floor(x + 0.5)


@njit(cache=True, error_model="numpy", fastmath=True)
def radial_solve(rho, air, thick, n):
    """Tan θ of a ray that crosses a lateral distance ``rho`` over an air path and a medium.

    The air path is ``air`` long, followed by a path ``thick`` in a medium of relative index
    ``n`` (Snell: sin θ = n sin θ_medium).
    """
    if thick == 0.0 or rho == 0.0:
        return rho / air
    m = rho / (air + thick / n)
    for _ in range(30):
        q = 1.0 + m * m
        rq = 1.0 / math.sqrt(q)
        sg = m * rq / n                      # sin of the angle in the medium
        cg2 = 1.0 - sg * sg
        cg = math.sqrt(cg2)
        f = air * m + thick * sg / cg - rho
        # d(tan θ_medium)/dm = (1/n) q^(-3/2) / cos³θ_medium
        d = air + thick * rq * rq * rq / (n * cg2 * cg)
        step = f / d
        m -= step
        if abs(step) <= 1e-15 * (1.0 + abs(m)):
            break
    return m


@njit(cache=True, error_model="numpy", fastmath=True)
def lenslet_at(x, y, g):
    """Lenslet hit at (x, y) on the lenslet plane: (index k, centre cx, cy); k = -1 if none."""
    c, s = g[G_COSG], g[G_SING]
    u = c * x + s * y - g[G_OFFS]
    v = -s * x + c * y - g[G_OFFT]
    rows, cols = int(g[G_ROWS]), int(g[G_COLS])
    p, rs = g[G_PITCH], g[G_ROWSP]
    rf = v / rs + (rows - 1) * 0.5
    best_k, best_u, best_v = -1, 0.0, 0.0
    if g[G_HEX] > 0.5:
        # nearest centre of the unbounded lattice (its Voronoi cell is the hexagon), then
        # keep it only if that lenslet exists
        r0 = int(math.floor(rf))
        best_d, best_r, best_c = 1e300, 0, 0
        for r in range(r0, r0 + 2):
            shift = 0.5 * (r % 2) - g[G_HEXSHIFT]
            cc = int(_round(u / p + (cols - 1) * 0.5 - shift))
            su = (cc - (cols - 1) * 0.5 + shift) * p
            sv = (r - (rows - 1) * 0.5) * rs
            d = (u - su) ** 2 + (v - sv) ** 2
            if d < best_d:
                best_d, best_r, best_c, best_u, best_v = d, r, cc, su, sv
        if best_r < 0 or best_r >= rows or best_c < 0 or best_c >= cols:
            return -1, 0.0, 0.0
        best_k = best_r * cols + best_c
    else:
        r = int(_round(rf))
        cc = int(_round(u / p + (cols - 1) * 0.5))
        if r < 0 or r >= rows or cc < 0 or cc >= cols:
            return -1, 0.0, 0.0
        best_k = r * cols + cc
        best_u = (cc - (cols - 1) * 0.5) * p
        best_v = (r - (rows - 1) * 0.5) * rs
    uu, vv = best_u + g[G_OFFS], best_v + g[G_OFFT]
    return best_k, c * uu - s * vv, s * uu + c * vv


@njit(cache=True, error_model="numpy", fastmath=True)
def through_lenslet(hx, hy, dx, dy, dz, cx, cy, g):
    """From the lenslet plane to the sensor.

    (hx, hy): hit on the lenslet plane; (dx, dy, dz): unit direction in the medium just before
    the lenslets (glass with a substrate, else air); (cx, cy): lenslet centre. Returns
    (ok, sx, sy), the sensor position in metres.
    """
    n = g[G_N]
    if g[G_THESIS] < 0.5 and g[G_T] > 0.0:
        ax, ay = n * dx, n * dy            # glass -> air at the lenslet surface
        q = 1.0 - ax * ax - ay * ay
        if q <= 0.0:                        # total internal reflection
            return False, 0.0, 0.0
        az = math.sqrt(q)
        mx, my = ax / az, ay / az
    else:
        mx, my = dx / dz, dy / dz
    fl = g[G_FL]
    mx -= (hx - cx) / fl
    my -= (hy - cy) / fl
    fb = g[G_FBAR]
    return True, hx + fb * mx, hy + fb * my


@njit(cache=True, error_model="numpy", fastmath=True)
def trace_image_ray(x0, y0, z0, mx, my, g):
    """Trace an image-space ray (air slopes mx, my from (x0, y0, z0)) to the sensor.

    Returns (k, sx, sy): lenslet index (-1: the ray misses the array or is lost) and the
    sensor position in metres.
    """
    t = g[G_T]
    if t > 0.0:
        l3 = g[G_L3]
        x = x0 + mx * (l3 - z0)
        y = y0 + my * (l3 - z0)
        inv = 1.0 / math.sqrt(1.0 + mx * mx + my * my)
        n = g[G_N]
        dx, dy = mx * inv / n, my * inv / n      # Snell: tangential n·d conserved
        dz = math.sqrt(1.0 - dx * dx - dy * dy)
        x += dx / dz * t
        y += dy / dz * t
    else:
        zm = g[G_ZMLA]
        x = x0 + mx * (zm - z0)
        y = y0 + my * (zm - z0)
        inv = 1.0 / math.sqrt(1.0 + mx * mx + my * my)
        dx, dy, dz = mx * inv, my * inv, inv
    k, cx, cy = lenslet_at(x, y, g)
    if k < 0:
        return -1, 0.0, 0.0
    ok, sx, sy = through_lenslet(x, y, dx, dy, dz, cx, cy, g)
    if not ok:
        return -1, 0.0, 0.0
    return k, sx, sy


@njit(cache=True, error_model="numpy", fastmath=True)
def splat(img, sx, sy, w, g):
    """Add weight ``w`` at sensor position (sx, sy) metres into ``img``.

    Bilinearly (the area of a pixel box around the point; ``g[G_SPLAT] = 0``) or wholly into
    the pixel that holds the point (``g[G_SPLAT] = 1``), at pixel coordinates shifted by
    ``(g[G_SHIFTR], g[G_SHIFTC])``.
    """
    pix = g[G_PIX]
    nr, nc = img.shape
    col = sx / pix + (g[G_NCOLS] - 1) * 0.5 + g[G_SHIFTC]
    row = sy / pix + (g[G_NROWS] - 1) * 0.5 + g[G_SHIFTR]
    if g[G_SPLAT] > 0.5:
        ri = int(math.floor(row + 0.5))
        ci = int(math.floor(col + 0.5))
        if ri >= 0 and ri < nr and ci >= 0 and ci < nc:
            img[ri, ci] += w
        return
    r0 = math.floor(row)
    c0 = math.floor(col)
    fr = row - r0
    fc = col - c0
    r0i, c0i = int(r0), int(c0)
    if r0i >= 0 and r0i < nr:
        if c0i >= 0 and c0i < nc:
            img[r0i, c0i] += w * (1.0 - fr) * (1.0 - fc)
        if c0i + 1 >= 0 and c0i + 1 < nc:
            img[r0i, c0i + 1] += w * (1.0 - fr) * fc
    if r0i + 1 >= 0 and r0i + 1 < nr:
        if c0i >= 0 and c0i < nc:
            img[r0i + 1, c0i] += w * fr * (1.0 - fc)
        if c0i + 1 >= 0 and c0i + 1 < nc:
            img[r0i + 1, c0i + 1] += w * fr * fc


# ---- counter-based random numbers (deterministic whatever the thread schedule) -------------

@njit(cache=True, inline="always", error_model="numpy", fastmath=True)
def _splitmix(x):
    x = (x + np.uint64(0x9E3779B97F4A7C15))
    z = x
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@njit(cache=True, inline="always", error_model="numpy", fastmath=True)
def uniform01(seed, i, j, stream):
    """A uniform number in [0, 1) from (seed, i, j, stream) by splitmix64 hashing."""
    h = _splitmix(np.uint64(seed) ^ (np.uint64(i) * np.uint64(0xD1B54A32D192ED03)))
    h = _splitmix(h ^ (np.uint64(j) * np.uint64(0xABC98388FB8FAC03)))
    h = _splitmix(h ^ np.uint64(stream))
    return (h >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@njit(cache=True, inline="always", error_model="numpy", fastmath=True)
def concentric_disc(a, b):
    """Shirley-Chiu map of the unit square to the unit disc (keeps stratification)."""
    a = 2.0 * a - 1.0
    b = 2.0 * b - 1.0
    if a == 0.0 and b == 0.0:
        return 0.0, 0.0
    if abs(a) > abs(b):
        r, phi = a, (math.pi / 4.0) * (b / a)
    else:
        r, phi = b, math.pi / 2.0 - (math.pi / 4.0) * (a / b)
    return r * math.cos(phi), r * math.sin(phi)


# ---- object space --------------------------------------------------------------------------

@njit(cache=True, error_model="numpy", fastmath=True)
def object_ray_to_lens(px, py, pz, lx, ly, g):
    """Air slopes (mx, my) at the lens plane of the ray from a source to a lens-plane point.

    The ray runs from the source (px, py, pz), pz < 0, to the lens-plane point (lx, ly, 0),
    refracted exactly at the external interface.
    """
    rx, ry = lx - px, ly - py
    if g[G_HASEXT] > 0.5 and pz < g[G_ZINT]:
        rho = math.sqrt(rx * rx + ry * ry)
        if rho == 0.0:
            return 0.0, 0.0
        air = -g[G_ZINT]                    # l2
        depth = g[G_ZINT] - pz              # path in the medium
        m = radial_solve(rho, air, depth, g[G_NEXT])
        return m * rx / rho, m * ry / rho
    return rx / (-pz), ry / (-pz)


@njit(cache=True, error_model="numpy", fastmath=True)
def paraxial_image(px, py, pz, g):
    """Paraxial image (x, y, z) of a source point through the interface and main lens."""
    s = -pz
    if g[G_HASEXT] > 0.5 and pz < g[G_ZINT]:
        l2 = -g[G_ZINT]
        s = l2 + (s - l2) / g[G_NEXT]
    f = g[G_FM]
    if s <= f * (1.0 + 1e-9):
        return 0.0, 0.0, -1.0
    zi = 1.0 / (1.0 / f - 1.0 / s)
    return -px * zi / s, -py * zi / s, zi


@njit(nogil=True, cache=True, error_model="numpy", fastmath=True)
def render_sources(sources, weights, half_size, n_samples, seed, first, ruler, g, out, lo, hi):
    """Render point (or small square area) sources through the whole camera.

    Parameters
    ----------
    sources : (N, 3) float64
        Source positions (x, y, z) in camera coordinates, z < 0, metres.
    weights : (N,) float64
        Emitted energy of each source collected by the full pupil.
    half_size : (2,) float64
        Half-size (x, y) of a square emitting area around each source (0 for points), m.
    n_samples : int
        Aperture samples per source, drawn on a jittered q × q grid (q = ceil(sqrt(n))).
    seed : int
    first : int
        Global index of ``sources[0]``: the random stream of a source is fixed by
        (seed, first + i), so splitting the sources into batches changes nothing.
    ruler : (3,) float64
        ``(spacing, tick_width, tick_reflectance)`` of a tick pattern along x (spacing 0: no
        pattern), evaluated at each sampled emitting point.
    g : geometry vector
    out : (n_chunks, rows, cols) float64 accumulators, one per parallel chunk
    lo, hi : int
        The chunks this call renders, ``lo <= chunk < hi``; chunk ``ch`` renders sources
        ``ch, ch + n_chunks, ...`` into ``out[ch]`` (:func:`plenopiv._threads.run_slices`
        runs the chunks in parallel).
    """
    n_chunks = out.shape[0]
    n_src = sources.shape[0]
    q = int(math.ceil(math.sqrt(n_samples)))
    e = g[G_E]
    rp = g[G_RPUPIL]
    f = g[G_FM]
    for ch in range(lo, hi):
        img = out[ch]
        for i in range(ch, n_src, n_chunks):
            px0, py0, pz = sources[i, 0], sources[i, 1], sources[i, 2]
            # sampling disc on the lens plane: the pre-image of the exit pupil (the lens
            # aperture itself when the exit pupil sits at the lens)
            cxs, cys, rs = 0.0, 0.0, rp
            if e != 0.0:
                qx, qy, qz = paraxial_image(px0, py0, pz, g)
                if qz > e:
                    k = qz / (qz - e)
                    cxs, cys, rs = -qx * e / (qz - e), -qy * e / (qz - e), 1.02 * rp * k
            w0 = weights[i] * (rs * rs) / (rp * rp) / (q * q)
            for a in range(q):
                for b in range(q):
                    j = a * q + b
                    gi = first + i
                    ua = (a + uniform01(seed, gi, j, 0)) / q
                    ub = (b + uniform01(seed, gi, j, 1)) / q
                    dx, dy = concentric_disc(ua, ub)
                    lx, ly = cxs + rs * dx, cys + rs * dy
                    px, py = px0, py0
                    w = w0
                    if half_size[0] > 0.0 or half_size[1] > 0.0:
                        px += (2.0 * uniform01(seed, gi, j, 2) - 1.0) * half_size[0]
                        py += (2.0 * uniform01(seed, gi, j, 3) - 1.0) * half_size[1]
                    if ruler[0] > 0.0:
                        frac = px / ruler[0] - math.floor(px / ruler[0] + 0.5)
                        if abs(frac) * ruler[0] < 0.5 * ruler[1]:
                            w *= ruler[2]
                    mx, my = object_ray_to_lens(px, py, pz, lx, ly, g)
                    mx -= lx / f                     # ideal thin main lens
                    my -= ly / f
                    if e != 0.0:
                        ex, ey = lx + mx * e, ly + my * e
                        if ex * ex + ey * ey > rp * rp:
                            continue
                    kk, sx, sy = trace_image_ray(lx, ly, 0.0, mx, my, g)
                    if kk >= 0:
                        splat(img, sx, sy, w, g)


@njit(nogil=True, cache=True, error_model="numpy", fastmath=True)
def render_lenslet_bundles(centres, weights, cell_points, pupil_points, collimated, g, out,
                           lo, hi):
    """Render, lenslet by lenslet, the light of a uniform source seen through a stop.

    Each ray goes from a pupil point (x, y, e) (or arrives collimated along z) to a point of
    a lenslet's cell on the lenslet plane; the ray that joins them through the substrate is
    solved exactly (Snell, Newton). Symmetric point sets keep each spot's centroid exact.

    Parameters
    ----------
    centres : (K, 2) lenslet centres (x, y), m
    weights : (K,) energy per lenslet
    cell_points : (M, 2) offsets inside a lenslet cell in the lattice frame (unrotated), m
    pupil_points : (P, 2) points of the stop at z = e, m
    collimated : bool, light along +z (lens removed), pupil_points unused
    out, lo, hi : the accumulators and the chunks this call renders, as in
        :func:`render_sources`
    """
    n_chunks = out.shape[0]
    n_len = centres.shape[0]
    c, s = g[G_COSG], g[G_SING]
    t, n = g[G_T], g[G_N]
    air = g[G_L3] - g[G_E]
    n_cell = cell_points.shape[0]
    n_pup = 1 if collimated else pupil_points.shape[0]
    for ch in range(lo, hi):
        img = out[ch]
        for k in range(ch, n_len, n_chunks):
            cx, cy = centres[k, 0], centres[k, 1]
            w = weights[k] / (n_cell * n_pup)
            for a in range(n_cell):
                ox, oy = cell_points[a, 0], cell_points[a, 1]
                hx = cx + c * ox - s * oy
                hy = cy + s * ox + c * oy
                for p in range(n_pup):
                    if collimated:
                        dx, dy, dz = 0.0, 0.0, 1.0
                    else:
                        rx = hx - pupil_points[p, 0]
                        ry = hy - pupil_points[p, 1]
                        rho = math.sqrt(rx * rx + ry * ry)
                        m = radial_solve(rho, air, t, n)
                        sn = m / math.sqrt(1.0 + m * m)
                        if t > 0.0:
                            sn /= n
                        cs = math.sqrt(1.0 - sn * sn)
                        if rho > 0.0:
                            dx, dy, dz = sn * rx / rho, sn * ry / rho, cs
                        else:
                            dx, dy, dz = 0.0, 0.0, 1.0
                    ok, sx, sy = through_lenslet(hx, hy, dx, dy, dz, cx, cy, g)
                    if ok:
                        splat(img, sx, sy, w, g)


@njit(parallel=True, cache=True, error_model="numpy", fastmath=True)
def trace_image_rays(x0, y0, z0, mx, my, g):
    """Vectorised :func:`trace_image_ray` (for tests and the light-field code)."""
    n = x0.shape[0]
    k = np.empty(n, np.int64)
    sx = np.empty(n)
    sy = np.empty(n)
    for i in prange(n):
        k[i], sx[i], sy[i] = trace_image_ray(x0[i], y0[i], z0[i], mx[i], my[i], g)
    return k, sx, sy


@njit(parallel=True, cache=True, error_model="numpy", fastmath=True)
def object_rays_to_lens(sources, lens_points, g):
    """Air slopes at the lens plane for each (source, lens point) pair, shape (N, 2)."""
    n = sources.shape[0]
    out = np.empty((n, 2))
    for i in prange(n):
        out[i, 0], out[i, 1] = object_ray_to_lens(sources[i, 0], sources[i, 1], sources[i, 2],
                                                  lens_points[i, 0], lens_points[i, 1], g)
    return out


def n_threads() -> int:
    """Threads numba uses for the parallel kernels."""
    return numba.get_num_threads()


# ---- plain-NumPy twins of the kernels -------------------------------------------------------


def radial_solve_numpy(rho, air, thick, n):
    """NumPy twin of :func:`radial_solve` (vectorised over ``rho``)."""
    rho = np.asarray(rho, dtype=float)
    if thick == 0.0:
        return rho / air
    m = rho / (air + thick / n)
    for _ in range(40):
        s = m / np.sqrt(1 + m * m)
        sg = s / n
        cg = np.sqrt(1 - sg * sg)
        f = air * m + thick * sg / cg - rho
        d = air + thick / n * (1 + m * m) ** -1.5 / cg ** 3
        m = m - f / d
    return m


def lenslet_at_numpy(x, y, g):
    """NumPy twin of :func:`lenslet_at`: nearest centre of a padded lattice, by brute force.

    A point whose nearest centre is a virtual (padding) lenslet hits none.
    """
    x, y = np.atleast_1d(x).astype(float), np.atleast_1d(y).astype(float)
    rows, cols = int(g[G_ROWS]), int(g[G_COLS])
    p, rs = g[G_PITCH], g[G_ROWSP]
    r, c = np.meshgrid(np.arange(-2, rows + 2), np.arange(-2, cols + 2), indexing="ij")
    r, c = r.ravel(), c.ravel()
    shift = (0.5 * (r % 2) - g[G_HEXSHIFT]) if g[G_HEX] > 0.5 else 0.0
    su = (c - (cols - 1) / 2 + shift) * p + g[G_OFFS]
    sv = (r - (rows - 1) / 2) * rs + g[G_OFFT]
    cs, sn = g[G_COSG], g[G_SING]
    cx, cy = cs * su - sn * sv, sn * su + cs * sv
    d2 = (x[:, None] - cx[None]) ** 2 + (y[:, None] - cy[None]) ** 2
    j = np.argmin(d2, axis=1)
    real = (r[j] >= 0) & (r[j] < rows) & (c[j] >= 0) & (c[j] < cols)
    k = np.where(real, r[j] * cols + c[j], -1)
    return k, cx[j], cy[j]


def _through_lenslet_directions_numpy(hx, hy, d, cx, cy, g):
    """NumPy twin of :func:`through_lenslet`; ``d`` is (N, 3) unit directions."""
    n = g[G_N]
    if g[G_THESIS] < 0.5 and g[G_T] > 0:
        a = n * d[:, :2]
        az = np.sqrt(1 - (a ** 2).sum(axis=1))
        m = a / az[:, None]
    else:
        m = d[:, :2] / d[:, 2:3]
    m = m - np.stack([hx - cx, hy - cy], axis=1) / g[G_FL]
    return np.stack([hx, hy], axis=1) + g[G_FBAR] * m


def trace_image_rays_numpy(x0, y0, z0, mx, my, g):
    """NumPy twin of :func:`trace_image_rays`, built from 3-D vector Snell."""
    o = np.stack([x0, y0, z0], axis=1).astype(float)
    d = np.stack([mx, my, np.ones_like(mx)], axis=1).astype(float)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, n = g[G_T], g[G_N]
    z_front = g[G_L3] if t > 0 else g[G_ZMLA]
    h = o + d * ((z_front - o[:, 2]) / d[:, 2])[:, None]
    if t > 0:
        d = _snell_numpy(d, np.array([0.0, 0.0, 1.0]), 1.0, n)
        h = h + d * (t / d[:, 2])[:, None]
    k, cx, cy = lenslet_at_numpy(h[:, 0], h[:, 1], g)
    s = _through_lenslet_directions_numpy(h[:, 0], h[:, 1], d, cx, cy, g)
    return k, s[:, 0], s[:, 1]


def _snell_numpy(d, normal, n1, n2):
    """Vector Snell refraction of unit directions ``d`` (N, 3) at a plane with unit ``normal``.

    ``t = (n1/n2) d + ((n1/n2) cos i - cos t) normal`` with ``cos i = d·normal``.
    """
    r = n1 / n2
    cos_i = d @ normal
    cos_t = np.sqrt(1 - r * r * (1 - cos_i ** 2))
    return r * d + (cos_t - r * cos_i)[:, None] * normal[None, :]


def splat_numpy(img, sx, sy, w, g):
    """NumPy twin of :func:`splat`, vectorised over points: adds them into ``img`` in place."""
    shape = img.shape
    sx, sy = np.atleast_1d(np.asarray(sx, float)), np.atleast_1d(np.asarray(sy, float))
    col = sx / g[G_PIX] + (g[G_NCOLS] - 1) / 2 + g[G_SHIFTC]
    row = sy / g[G_PIX] + (g[G_NROWS] - 1) / 2 + g[G_SHIFTR]
    w = np.broadcast_to(np.asarray(w, float), np.shape(sx))
    if g[G_SPLAT] > 0.5:
        rr, cc = np.floor(row + 0.5).astype(int), np.floor(col + 0.5).astype(int)
        ok = (rr >= 0) & (rr < shape[0]) & (cc >= 0) & (cc < shape[1])
        np.add.at(img, (rr[ok], cc[ok]), w[ok])
        return img
    r0, c0 = np.floor(row).astype(int), np.floor(col).astype(int)
    fr, fc = row - r0, col - c0
    for dr, dc, ww in ((0, 0, (1 - fr) * (1 - fc)), (0, 1, (1 - fr) * fc),
                       (1, 0, fr * (1 - fc)), (1, 1, fr * fc)):
        rr, cc = r0 + dr, c0 + dc
        ok = (rr >= 0) & (rr < shape[0]) & (cc >= 0) & (cc < shape[1])
        np.add.at(img, (rr[ok], cc[ok]), (w * ww)[ok])
    return img


def object_rays_to_lens_numpy(sources, lens_points, g):
    """NumPy twin of :func:`object_rays_to_lens` (exact Snell at the interface)."""
    p = np.asarray(sources, float)
    lpt = np.asarray(lens_points, float)
    r = lpt - p[:, :2]
    z = -p[:, 2]
    m = r / z[:, None]
    if g[G_HASEXT] > 0.5:
        behind = p[:, 2] < g[G_ZINT]
        rho = np.hypot(r[:, 0], r[:, 1])
        mm = np.array([radial_solve_numpy(rh, -g[G_ZINT], g[G_ZINT] - pz, g[G_NEXT])
                       for rh, pz in zip(rho, p[:, 2], strict=True)])
        with np.errstate(invalid="ignore", divide="ignore"):
            mr = np.where(rho[:, None] > 0, mm[:, None] * r / np.where(rho > 0, rho, 1)[:, None],
                          0.0)
        m = np.where(behind[:, None], mr, m)
    return m
