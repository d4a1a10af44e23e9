"""The light field: every lit pixel as a ray (s, t, u, v), perspective views and refocusing.

For a pixel at sensor position x under the lenslet with centre d and focal spot x_c
(DESIGN.md §4, thesis Eqs. 4.1/4.5 with the sign the thesis drops)::

    u = -(x - x_c) · S_i,eff / f̄          (aperture-plane position, metres)
    s = d                                 (lenslet centre on the lenslet plane)

and its conjugate on the nominal focal plane is X_f = s/M = -s S_o,eff/S_i,eff. In object space
(effective coordinates) the ray passes through (u, 0) at the lens and X_f at S_o,eff, so at
depth Z it is at X(Z) = u + (X_f - u)(S_o,eff + Z)/S_o,eff.

A pixel is a beam: its aperture cell is p_p S_i,eff/f̄ wide, its lenslet footprint on the focal
plane p_m S_o,eff/S_i,eff. Pixels whose cell lies mostly outside the aperture disc (f_m/N) never
receive light and are left out.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.conventions import pixel_to_sensor
from plenopiv.errors import CalibrationError
from plenopiv.lightfield import _kernels as _lk


class LightFieldWarning(UserWarning):
    """The light field's model does not match its calibration (micro-image size, rays)."""


# modelled and measured micro-image diameters may differ by this factor before a warning
MICRO_IMAGE_TOLERANCE = 1.25
# fewer rays per lenslet than this on average: the light field is nearly empty
MIN_RAYS_PER_LENSLET = 4.0


def micro_image_diameter_px(camera, image_distance: float, f_number: float) -> float:
    """Modelled micro-image diameter, px: the aperture ``f_m / N`` seen from the lenslets.

    ``f_m / N * f̄ / S_i`` on the sensor (divided by the plate's index with the "thesis" back
    side, whose rays keep their in-glass angle). :func:`light_field` takes each lenslet's
    pixels within this disc (plus a pixel).
    """
    d = camera.main_lens.focal_length / f_number
    mla = camera.microlens_array
    if mla.back_side == "thesis" and mla.substrate is not None:
        d /= mla.substrate.refractive_index
    return d * camera.microlens_array.sensor_distance / image_distance / camera.sensor.pixel_pitch


@dataclass(frozen=True)
class LightField:
    """The rays of the lit pixels of one camera calibration.

    Attributes
    ----------
    pixel : (P,) int64
        Flat pixel index ``row * n_cols + col``.
    lenslet : (P,) int32
        Index of the pixel's lenslet in the calibration.
    s : (P, 2) float64
        Lenslet centre (x, y) on the lenslet plane, metres.
    u : (P, 2) float64
        Aperture-plane position (x, y) of the pixel's ray, metres.
    lit : (P,) float64
        Fraction of the pixel's aperture cell inside the aperture disc.
    image_distance, object_distance : float
        Effective S_i and S_o, metres.
    aperture_radius : float
        Main-lens aperture radius f_m/(2N), metres.
    cell : float
        Aperture-cell width p_p S_i/f̄, metres.
    footprint : float
        Lenslet footprint on the nominal focal plane p_m S_o/S_i, metres.
    shape : tuple
        Sensor shape (rows, cols).
    """

    pixel: np.ndarray
    lenslet: np.ndarray
    s: np.ndarray
    u: np.ndarray
    lit: np.ndarray
    image_distance: float
    object_distance: float
    aperture_radius: float
    cell: float
    footprint: float
    shape: tuple[int, int]

    @property
    def n_rays(self) -> int:
        """Number of lit pixels (rays)."""
        return len(self.pixel)

    @property
    def magnification(self) -> float:
        """M = -S_i,eff/S_o,eff."""
        return -self.image_distance / self.object_distance

    @property
    def focal_plane_position(self) -> np.ndarray:
        """X_f = s/M, the ray's point on the nominal focal plane (P, 2), metres."""
        return self.s / self.magnification

    def position_at_depth(self, depth) -> np.ndarray:
        """Ray positions (P, 2) at effective depth Z (metres) from the nominal focal plane."""
        t = (self.object_distance + depth) / self.object_distance
        return self.u + (self.focal_plane_position - self.u) * t

    @property
    def alpha_range(self) -> tuple[float, float]:
        """The refocus parameters α this light field supports, ``(α_min, α_max)``.

        Refocusing moves a ray through aperture point u by ``u (1/α - 1)`` on the lenslet
        plane; α is supported while the rays from the aperture's edge move by at most half
        the smaller extent of the lenslet array, ``R |1/α - 1| <= W / 2`` (beyond it most
        views miss most of the array and the refocused image is empty). ``α_max`` is
        infinite when ``W / 2 >= R``.
        """
        if self.n_rays == 0:
            return (1.0, 1.0)
        w = float(np.min(np.ptp(self.s, axis=0))) + self.footprint * self.image_distance \
            / self.object_distance
        q = 0.5 * w / self.aperture_radius
        return (1.0 / (1.0 + q), math.inf if q >= 1.0 else 1.0 / (1.0 - q))

    def values(self, image) -> np.ndarray:
        """The image's value for every ray (P,)."""
        img = np.asarray(image)
        if img.shape != tuple(self.shape):
            raise CalibrationError(f"image is {img.shape}, the calibration's sensor is "
                                   f"{tuple(self.shape)}")
        return img.reshape(-1)[self.pixel]


def light_field(calibration: Calibration, *, f_number: float | None = None,
                min_lit: float = 0.5, edge_centroid: bool = True) -> LightField:
    """Map every lit pixel of the calibrated camera to its ray.

    Parameters
    ----------
    calibration : Calibration
    f_number : float, optional
        Aperture of the recording (default: the camera's f-number).
    min_lit : float
        Keep pixels whose aperture cell is at least this fraction inside the aperture.
    edge_centroid : bool
        Trace a pixel cut by the aperture's edge through the centroid of its cell's lit part
        (default), or through the cell centre (the model of the matrix-free
        :class:`~plenopiv.reconstruction.lattice.LatticeProjector`).

    Warns
    -----
    LightFieldWarning
        When the f-number makes the modelled micro-images more than 1.25 times larger or
        smaller than the white image of the calibration shows
        (``calibration.extra["micro_image_diameter_px"]``), when they are larger than the
        micro-image pitch, or when fewer than 4 rays per lenslet remain: the views and
        refocused images would be mostly blank or NaN. Each message names ``f_number``.
    """
    cam = calibration.camera
    si = calibration.image_distance
    so = 1.0 / (1.0 / cam.main_lens.focal_length - 1.0 / si)
    fbar = cam.microlens_array.sensor_distance
    pp = cam.sensor.pixel_pitch
    n_f = cam.main_lens.f_number if f_number is None else f_number
    radius = cam.main_lens.focal_length / n_f / 2
    if cam.microlens_array.back_side == "thesis" and cam.microlens_array.substrate is not None:
        # rays keep their in-glass angle behind the lenslets: the micro-images, and so the
        # aperture as the pixels see it through u = -(x - x_c) S_i/f̄, are n times smaller
        # (the depth scale this leaves is the internal correction, thesis Eq. 5.1)
        radius /= cam.microlens_array.substrate.refractive_index
    cell = pp * si / fbar
    shape = cam.sensor.shape

    spots = np.asarray(calibration.focal_spot_px, float)
    centres_m = pixel_to_sensor(calibration.centre_px, shape, pp)
    # pixels of each micro-image: within the aperture image radius (R f̄/S_i) and within half
    # a micro-image pitch of its own spot (so that no pixel belongs to two lenslets)
    r_img_px = radius * fbar / si / pp
    pitch_px = cam.pitch_px * (1 + fbar / si)
    _check_micro_images(calibration, n_f, 2.0 * r_img_px, pitch_px)
    r_max = min(r_img_px + 1.0, 0.5 * pitch_px)
    half = int(math.ceil(r_max)) + 1
    off = np.arange(-half, half + 1)
    dr, dc = np.meshgrid(off, off, indexing="ij")
    dr, dc = dr.ravel(), dc.ravel()
    base = np.rint(spots).astype(int)
    rows = base[:, 0, None] + dr[None, :]
    cols = base[:, 1, None] + dc[None, :]
    rel_r = rows - spots[:, 0, None]
    rel_c = cols - spots[:, 1, None]
    inside = ((rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
              & (rel_r ** 2 + rel_c ** 2 <= r_max ** 2))
    # aperture position of each pixel (x along cols, y along rows)
    ux = -rel_c * pp * si / fbar
    uy = -rel_r * pp * si / fbar
    lit, dux, duy = _lit_inside(ux, uy, inside, cell, radius)
    # a pixel cut by the aperture's edge sees only the lit part of its cell: its ray goes
    # through the centroid of that part, not through the cell centre
    if edge_centroid:
        ux, uy = ux + dux, uy + duy
    keep = inside & (lit >= min_lit)
    k_idx, _ = np.nonzero(keep)
    pix = (rows[keep].astype(np.int64) * shape[1] + cols[keep])
    order = np.argsort(pix, kind="stable")
    pix = pix[order]
    if len(pix) and np.any(np.diff(pix) == 0):
        raise CalibrationError("two lenslets claim the same pixel: the focal spots are closer "
                               "than the aperture image; check the f-number and calibration")
    n_lenslets = max(len(spots), 1)
    if len(pix) < MIN_RAYS_PER_LENSLET * n_lenslets:
        warnings.warn(
            f"the light field keeps {len(pix)} rays for {n_lenslets} lenslets "
            f"({len(pix) / n_lenslets:.2g} per lenslet, fewer than {MIN_RAYS_PER_LENSLET:g}): "
            f"with f_number = {n_f:g} the modelled micro-images are {2 * r_img_px:.2f} px "
            "across; views and refocused images will be mostly blank or NaN (check f_number)",
            LightFieldWarning, stacklevel=2)
    return LightField(
        pixel=pix, lenslet=k_idx[order].astype(np.int32), s=centres_m[k_idx[order]],
        u=np.stack([ux[keep], uy[keep]], axis=1)[order], lit=lit[keep][order],
        image_distance=si, object_distance=so, aperture_radius=radius, cell=cell,
        footprint=cam.microlens_array.pitch * so / si, shape=shape)


def _check_micro_images(calibration: Calibration, n_f: float, model_px: float,
                        pitch_px: float) -> None:
    """Warn when the modelled micro-image size contradicts the calibration (see light_field)."""
    measured = calibration.extra.get("micro_image_diameter_px")
    if measured is not None and np.isfinite(measured) and measured > 0:
        ratio = model_px / float(measured)
        if not 1.0 / MICRO_IMAGE_TOLERANCE <= ratio <= MICRO_IMAGE_TOLERANCE:
            implied = n_f * ratio
            warnings.warn(
                f"f_number = {n_f:g} makes the micro-images {model_px:.1f} px across, but the "
                f"white image of the calibration shows {float(measured):.1f} px (as from "
                f"f_number = {implied:.3g}); the light field takes each lenslet's pixels "
                f"within the modelled size, so it {'misses' if ratio < 1 else 'adds dark'} "
                "pixels: set [main_lens] f_number (or f_number=) to the recording's aperture",
                LightFieldWarning, stacklevel=3)
            return
    if model_px > MICRO_IMAGE_TOLERANCE * pitch_px:
        warnings.warn(
            f"f_number = {n_f:g} makes the micro-images {model_px:.1f} px across, more than "
            f"their pitch {pitch_px:.1f} px: they would overlap, and each lenslet keeps only "
            "the pixels within half a pitch (check f_number)", LightFieldWarning, stacklevel=3)


def _lit_inside(ux, uy, inside, cell, radius):
    """:func:`_lit_fraction` (numba) of the pixels ``inside``; zeros elsewhere."""
    out = [np.zeros(ux.shape) for _ in range(3)]
    for full, part in zip(out, _lk.lit_fraction(ux[inside], uy[inside], cell, radius, 8),
                          strict=True):
        full[inside] = part
    return out


def _lit_fraction(ux, uy, cell, radius, n=8):
    """Fraction of a cell × cell square centred at (ux, uy) inside the disc, and the offset
    of the centroid of its inside part (n × n samples; only cells that the disc's edge
    crosses are sampled, the others are wholly lit or wholly dark)."""
    ux, uy = np.asarray(ux, float), np.asarray(uy, float)
    dist = np.hypot(ux, uy)
    reach = cell * math.sqrt(0.5)
    lit = (dist + reach <= radius).astype(float)
    sx = np.zeros(ux.shape)
    sy = np.zeros(ux.shape)
    edge = np.abs(dist - radius) < reach
    ex, ey = ux[edge], uy[edge]
    o = (np.arange(n) - (n - 1) / 2) * (cell / n)
    count = np.zeros(ex.shape)
    ax = np.zeros(ex.shape)
    ay = np.zeros(ex.shape)
    for a in o:
        for b in o:
            inside = (ex + a) ** 2 + (ey + b) ** 2 <= radius ** 2
            count += inside
            ax += a * inside
            ay += b * inside
    safe = np.maximum(count, 1)
    lit[edge] = count / (n * n)
    sx[edge] = ax / safe
    sy[edge] = ay / safe
    return lit, sx, sy


PERSPECTIVE_INTERPOLATIONS = ("nearest", "linear")
REFOCUS_METHODS = ("splat", "fourier")


def perspective_view(image, lf: LightField, grid_index, u=(0.0, 0.0), *,
                     interpolation: str = "nearest") -> np.ndarray:
    """Return the sub-aperture image seen through aperture point ``u`` (metres).

    Parameters
    ----------
    image : ndarray, shape ``lf.shape``
        Recorded (ideally dark-subtracted and flat-fielded) raw image.
    lf : LightField
    grid_index : (N, 2) int
        Lattice index ``(row, col)`` of every calibration lenslet (``Calibration.grid_index``).
    u : (2,) float
        Aperture-plane point ``(x, y)``, metres (``(0, 0)``: the pupil centre, the central view).
    interpolation : {"nearest", "linear"}
        ``"nearest"`` (default): for each lenslet, the value of its pixel whose aperture position
        is nearest to ``u`` (within 0.75 of a cell); lenslets with none are NaN.
        ``"linear"``: the image bilinearly interpolated at the exact sensor point that sees ``u``
        through the lenslet, ``x = x_c - u f̄/S_i`` (x_c its focal spot); NaN where one of the
        four pixels is not a lit pixel of that lenslet. Every lenslet then sees exactly the same
        aperture point, so views at nearby ``u`` differ only by parallax (what disparity
        measurements and :func:`refocus` with ``method="fourier"`` need).

    Returns
    -------
    ndarray, shape (lenslet rows, lenslet cols)
        Indexed by ``grid_index``; float64, NaN where a lenslet has no value.
    """
    if interpolation not in PERSPECTIVE_INTERPOLATIONS:
        raise ValueError(f"interpolation = {interpolation!r}: expected one of "
                         f"{PERSPECTIVE_INTERPOLATIONS}")
    gi = _check_grid_index(grid_index, lf)
    out = np.full((gi[:, 0].max() + 1, gi[:, 1].max() + 1), np.nan)
    if interpolation == "linear":
        vals = _views_linear(image, lf, len(gi), np.asarray(u, float).reshape(1, 2))[0]
        out[gi[:, 0], gi[:, 1]] = vals
        return out
    vals = lf.values(image).astype(float)
    d2 = ((lf.u - np.asarray(u, float)) ** 2).sum(axis=1)
    ok = np.flatnonzero(d2 <= (0.75 * lf.cell) ** 2)
    k = lf.lenslet[ok]
    # nearest ray of each lenslet; lexsort is stable, so ties keep the lowest pixel index
    order = np.lexsort((d2[ok], k))
    first = np.ones(len(order), bool)
    first[1:] = k[order][1:] != k[order][:-1]
    sel = ok[order[first]]
    kk = lf.lenslet[sel]
    out[gi[kk, 0], gi[kk, 1]] = vals[sel]
    return out


def refocus(image, lf: LightField, alpha: float, *, pitch: float | None = None,
            shape_lenslets=None, method: str = "splat", grid_index=None) -> np.ndarray:
    """Refocused image on a synthetic lenslet plane at α S_i (thesis §2.3, Ng 2005).

    A ray through aperture point u and lenslet centre s meets the plane z = α S_i at
    s' = u + α (s - u); rescaled by 1/α (the magnification of the nominal plane is kept) it
    lands at ``s'/α = s + u (1/α - 1)`` on the lenslet plane. The refocused image is the
    average of the rays landing at each point.

    Parameters
    ----------
    image : ndarray, shape ``lf.shape``
        Recorded raw image (dark-subtracted and flat-fielded for real data). Rays whose value
        is not finite (NaN marks pixels to ignore) are left out.
    lf : LightField
    alpha : float
        α > 1 focuses in front of the nominal focal plane (nearer the camera), α < 1 behind it;
        α = 1 is the nominal focal plane. It must lie within ``lf.alpha_range``
        (:attr:`LightField.alpha_range`), else ValueError gives that range.
    pitch : float
        ``method="splat"`` only: output grid spacing on the lenslet plane, metres.
    shape_lenslets : (rows, cols)
        ``method="splat"`` only: output shape; the grid is centred on the optical axis.
    method : {"splat", "fourier"}
        ``"splat"`` (default): each ray's value is splatted bilinearly onto the axis-centred
        grid at ``s'/α`` and normalised by the splatted weight. ``"fourier"``: shift-and-add
        of perspective views on the lenslet lattice: views at aperture points u one cell
        apart (those whose cell lies wholly inside the aperture), each bilinearly sampled
        (``perspective_view(..., interpolation="linear")``), shifted by ``u (1/α - 1)`` with
        an exact Fourier (band-limited) shift and averaged, with the views' NaN masks shifted
        alongside to normalise. Needs ``grid_index``.
    grid_index : (N, 2) int
        ``method="fourier"`` only: lattice index of every calibration lenslet.

    Returns
    -------
    ndarray
        ``"splat"``: shape ``shape_lenslets``; ``"fourier"``: (lenslet rows, lenslet cols),
        indexed like :func:`perspective_view`. NaN where no ray lands (splat) or where fewer
        than half of the views cover the point (fourier).

    Notes
    -----
    Choosing a method. The splat resamples the rays onto a fixed grid, and how much that
    blurs depends on α: at α = 1 all rays of a lenslet land on one point (the integral
    image, resampled by the bilinear kernel according to where the lenslet centres fall on the
    grid), while at α ≠ 1 they spread over a disc of radius R|1/α - 1|. A sharpness measure
    evaluated on splatted images over α therefore has a kink at α = 1 and is pulled onto it:
    for ray-traced particles on the plane α = 1.004 it peaks at 1.000, and on the plenoptomos
    letters image at 1.000, where parallax puts the letters at about 1.017. The Fourier
    shift-and-add keeps every output sample on the lenslet lattice and shifts by band-limited
    (sinc) interpolation, which keeps each view's spectrum, so only the alignment of the
    views changes with α: use it for depth from focus (sharpness over α); it finds the
    particles' 1.004 to 0.001. The views are zero-padded before the FFT (no wrap-around).
    Its output is at lenslet resolution; the splat can also be evaluated on finer grids.
    Shifts are converted to lattice units with the lattice basis fitted to the lenslet
    centres, so a rotated or anisotropic lattice is handled.
    """
    if not alpha > 0:
        raise ValueError(f"alpha = {alpha!r}: expected > 0")
    lo, hi = lf.alpha_range
    if not lo <= alpha <= hi:
        raise ValueError(
            f"alpha = {alpha!r} is outside the range this light field supports, "
            f"{lo:.4g} <= alpha <= {hi:.4g}: beyond it the rays from the aperture's edge move "
            "by more than half the lenslet array and the refocused image is empty "
            "(LightField.alpha_range)")
    if method not in REFOCUS_METHODS:
        raise ValueError(f"method = {method!r}: expected one of {REFOCUS_METHODS}")
    if method == "fourier":
        if grid_index is None:
            raise ValueError('method = "fourier" needs grid_index (the calibration\'s lattice '
                             "indices); pitch and shape_lenslets do not apply")
        if pitch is not None or shape_lenslets is not None:
            raise ValueError('method = "fourier" returns the image on the lenslet lattice: '
                             "leave pitch and shape_lenslets unset")
        return _refocus_fourier(image, lf, float(alpha), grid_index)
    if pitch is None or shape_lenslets is None:
        raise ValueError('method = "splat" needs pitch (metres) and shape_lenslets (rows, cols)')
    if not pitch > 0:
        raise ValueError(f"pitch = {pitch!r}: expected > 0 metres")
    vals = lf.values(image).astype(float)
    # the aperture point u lives on the lens plane; at the lenslet plane the ray has moved
    # from u (z = 0) to s (z = S_i): at z = α S_i it is at u + α (s - u)
    sp = (lf.u + alpha * (lf.s - lf.u)) / alpha
    rows, cols = (int(v) for v in shape_lenslets)
    fin = np.isfinite(vals)
    sp, vals = sp[fin], vals[fin]
    fc = sp[:, 0] / pitch + (cols - 1) / 2
    fr = sp[:, 1] / pitch + (rows - 1) / 2
    n = (rows + 1) * (cols + 1)
    acc = np.zeros(n)
    wgt = np.zeros(n)
    r0, c0 = np.floor(fr).astype(int), np.floor(fc).astype(int)
    ar, ac = fr - r0, fc - c0
    for drr, dcc, w in ((0, 0, (1 - ar) * (1 - ac)), (0, 1, (1 - ar) * ac),
                        (1, 0, ar * (1 - ac)), (1, 1, ar * ac)):
        rr, cc = r0 + drr, c0 + dcc
        ok = (rr >= 0) & (rr < rows) & (cc >= 0) & (cc < cols)
        idx = rr[ok] * (cols + 1) + cc[ok]
        acc += np.bincount(idx, (w * vals)[ok], minlength=n)
        wgt += np.bincount(idx, w[ok], minlength=n)
    out = np.where(wgt > 0, acc / np.where(wgt > 0, wgt, 1), np.nan)
    return out.reshape(rows + 1, cols + 1)[:rows, :cols]


# ---- helpers: focal spots, bilinear views, Fourier shift-and-add ------------------------------


def _check_grid_index(grid_index, lf: LightField) -> np.ndarray:
    gi = np.asarray(grid_index)
    if gi.ndim != 2 or gi.shape[1] != 2 or len(gi) == 0:
        raise ValueError(f"grid_index has shape {gi.shape}: expected (N, 2) lattice indices")
    gi = gi.astype(int)
    if gi.min() < 0:
        raise ValueError("grid_index holds negative indices: expected lattice indices >= 0")
    if lf.n_rays and lf.lenslet.max() >= len(gi):
        raise ValueError(f"grid_index has {len(gi)} rows but the light field has lenslet "
                         f"{int(lf.lenslet.max())}: pass the calibration's grid_index")
    return gi


def _lenslet_spots_px(lf: LightField, n_lenslets: int) -> np.ndarray:
    """Recover every lenslet's focal spot (row, col), px, from its rays.

    NaN for a lenslet without a wholly lit pixel. Every ray satisfies
    ``u = -(x - x_c) S_i/f̄`` with the cell ``p_p S_i/f̄``, so ``x_c = x + u / cell`` in pixels.
    """
    # only wholly lit pixels: a pixel cut by the aperture edge has its ray moved to the
    # centroid of the lit part of its cell, so its u no longer marks the pixel centre
    full = np.flatnonzero(lf.lit >= 1.0 - 1e-9)
    rows, cols = np.divmod(lf.pixel[full], lf.shape[1])
    r = rows + lf.u[full, 1] / lf.cell
    c = cols + lf.u[full, 0] / lf.cell
    k = lf.lenslet[full]
    cnt = np.bincount(k, minlength=n_lenslets).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        sr = np.bincount(k, r, minlength=n_lenslets) / cnt
        sc = np.bincount(k, c, minlength=n_lenslets) / cnt
    return np.stack([sr, sc], axis=1)


def _lenslet_centres(lf: LightField, n_lenslets: int) -> np.ndarray:
    """Lenslet centre (x, y) metres of every lenslet from its rays; NaN without rays."""
    cnt = np.bincount(lf.lenslet, minlength=n_lenslets).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.stack([np.bincount(lf.lenslet, lf.s[:, i], minlength=n_lenslets) / cnt
                         for i in (0, 1)], axis=1)


def _view_sampler(image, lf: LightField, n_lenslets: int):
    """Prepare :func:`_views_linear`: the flat image, pixel owners and focal spots.

    Returns the image as a flat float array, the lenslet of every pixel (-1: none) and every
    lenslet's focal spot (row, col), px.
    """
    img = np.asarray(image)
    if img.shape != tuple(lf.shape):
        raise CalibrationError(f"image is {img.shape}, the calibration's sensor is "
                               f"{tuple(lf.shape)}")
    flat = img.reshape(-1).astype(float)
    owner = np.full(flat.size, -1, np.int64)
    owner[lf.pixel] = lf.lenslet
    return flat, owner, _lenslet_spots_px(lf, n_lenslets)


def _views_linear(image, lf: LightField, n_lenslets: int, us, sampler=None) -> np.ndarray:
    """Bilinear views: value of every lenslet (columns) at every aperture point ``us`` (rows).

    NaN where one of the four pixels around the sampled point is not a lit pixel of that
    lenslet (or its value is not finite). ``sampler`` is :func:`_view_sampler`'s result,
    to reuse it over many calls.
    """
    flat, owner, spots = sampler or _view_sampler(image, lf, n_lenslets)
    us = np.asarray(us, float).reshape(-1, 2)
    r = spots[None, :, 0] - us[:, None, 1] / lf.cell
    c = spots[None, :, 1] - us[:, None, 0] / lf.cell
    good = np.isfinite(r) & np.isfinite(c)
    r0 = np.floor(np.where(good, r, 0)).astype(np.int64)
    c0 = np.floor(np.where(good, c, 0)).astype(np.int64)
    ar, ac = r - r0, c - c0
    k = np.broadcast_to(np.arange(n_lenslets), r.shape)
    out = np.zeros(r.shape)
    n_rows, n_cols = lf.shape
    for dr, dc, w in ((0, 0, (1 - ar) * (1 - ac)), (0, 1, (1 - ar) * ac),
                      (1, 0, ar * (1 - ac)), (1, 1, ar * ac)):
        rr, cc = r0 + dr, c0 + dc
        inside = good & (rr >= 0) & (rr < n_rows) & (cc >= 0) & (cc < n_cols)
        idx = np.where(inside, rr * n_cols + cc, 0)
        good &= inside & (owner[idx] == k)
        out += w * flat[idx]
    out[~(good & np.isfinite(out))] = np.nan
    return out


def _aperture_samples(lf: LightField) -> np.ndarray:
    """Aperture points (x, y) metres one cell apart whose whole cell is inside the aperture."""
    n = int(math.floor(lf.aperture_radius / lf.cell))
    a = np.arange(-n, n + 1) * lf.cell
    ux, uy = np.meshgrid(a, a)
    ux, uy = ux.ravel(), uy.ravel()
    # the cell's farthest corner inside the disc
    keep = (np.abs(ux) + lf.cell / 2) ** 2 + (np.abs(uy) + lf.cell / 2) ** 2 \
        <= lf.aperture_radius ** 2
    if not keep.any():
        keep = np.hypot(ux, uy) == 0
    return np.stack([ux[keep], uy[keep]], axis=1)


def _refocus_fourier(image, lf: LightField, alpha: float, grid_index) -> np.ndarray:
    gi = _check_grid_index(grid_index, lf)
    n_k = len(gi)
    shape = (int(gi[:, 0].max()) + 1, int(gi[:, 1].max()) + 1)
    # lattice basis (metres per index step) from the lenslet centres: s = o + i b_r + j b_c
    centres = _lenslet_centres(lf, n_k)
    have = np.isfinite(centres[:, 0])
    if have.sum() < 3:
        raise CalibrationError("refocus: fewer than 3 lenslets have rays; cannot fit the lattice")
    design = np.column_stack([np.ones(have.sum()), gi[have, 0], gi[have, 1]])
    coef, *_ = np.linalg.lstsq(design, centres[have], rcond=None)
    basis = np.stack([coef[1], coef[2]], axis=1)      # columns b_r, b_c; rows x, y
    us = _aperture_samples(lf)
    shifts = np.linalg.solve(basis, (us * (1.0 / alpha - 1.0)).T).T   # (n_u, 2) (d_row, d_col)
    pad = int(math.ceil(np.abs(shifts).max())) + 2
    big = (shape[0] + 2 * pad, shape[1] + 2 * pad)
    ky = np.fft.fftfreq(big[0])[None, :, None]
    kx = np.fft.fftfreq(big[1])[None, None, :]
    num = np.zeros(big, complex)
    den = np.zeros(big, complex)
    chunk = 64
    sampler = _view_sampler(image, lf, n_k)
    for a in range(0, len(us), chunk):
        v = _views_linear(image, lf, n_k, us[a:a + chunk], sampler)
        stack = np.zeros((len(v), *big))
        mask = np.zeros((len(v), *big))
        ok = np.isfinite(v)
        stack[:, pad + gi[:, 0], pad + gi[:, 1]] = np.where(ok, v, 0.0)
        mask[:, pad + gi[:, 0], pad + gi[:, 1]] = ok
        sh = shifts[a:a + chunk]
        phase = np.exp(-2j * np.pi * (ky * sh[:, 0, None, None] + kx * sh[:, 1, None, None]))
        num += (np.fft.fft2(stack) * phase).sum(axis=0)
        den += (np.fft.fft2(mask) * phase).sum(axis=0)
    num_r = np.fft.ifft2(num).real[pad:pad + shape[0], pad:pad + shape[1]]
    den_r = np.fft.ifft2(den).real[pad:pad + shape[0], pad:pad + shape[1]]
    cover = den_r >= 0.5 * len(us)
    return np.where(cover, num_r / np.where(cover, den_r, 1.0), np.nan)
