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
from dataclasses import dataclass

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.conventions import pixel_to_sensor
from plenopiv.errors import CalibrationError


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

    def values(self, image) -> np.ndarray:
        """The image's value for every ray (P,)."""
        img = np.asarray(image)
        if img.shape != tuple(self.shape):
            raise CalibrationError(f"image is {img.shape}, the calibration's sensor is "
                                   f"{tuple(self.shape)}")
        return img.reshape(-1)[self.pixel]


def light_field(calibration: Calibration, *, f_number: float | None = None,
                min_lit: float = 0.5) -> LightField:
    """Map every lit pixel of the calibrated camera to its ray.

    Parameters
    ----------
    calibration : Calibration
    f_number : float, optional
        Aperture of the recording (default: the camera's f-number).
    min_lit : float
        Keep pixels whose aperture cell is at least this fraction inside the aperture.
    """
    cam = calibration.camera
    si = calibration.image_distance
    so = 1.0 / (1.0 / cam.main_lens.focal_length - 1.0 / si)
    fbar = cam.microlens_array.sensor_distance
    pp = cam.sensor.pixel_pitch
    n_f = cam.main_lens.f_number if f_number is None else f_number
    radius = cam.main_lens.focal_length / n_f / 2
    cell = pp * si / fbar
    shape = cam.sensor.shape

    spots = np.asarray(calibration.focal_spot_px, float)
    centres_m = pixel_to_sensor(calibration.centre_px, shape, pp)
    # pixels of each micro-image: within the aperture image radius (R f̄/S_i) and within half
    # a micro-image pitch of its own spot (so that no pixel belongs to two lenslets)
    r_img_px = radius * fbar / si / pp
    pitch_px = cam.pitch_px * (1 + fbar / si)
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
    lit = _lit_fraction(ux, uy, cell, radius)
    keep = inside & (lit >= min_lit)
    k_idx, _ = np.nonzero(keep)
    pix = (rows[keep].astype(np.int64) * shape[1] + cols[keep])
    order = np.argsort(pix, kind="stable")
    pix = pix[order]
    if len(pix) and np.any(np.diff(pix) == 0):
        raise CalibrationError("two lenslets claim the same pixel: the focal spots are closer "
                               "than the aperture image; check the f-number and calibration")
    return LightField(
        pixel=pix, lenslet=k_idx[order].astype(np.int32), s=centres_m[k_idx[order]],
        u=np.stack([ux[keep], uy[keep]], axis=1)[order], lit=lit[keep][order],
        image_distance=si, object_distance=so, aperture_radius=radius, cell=cell,
        footprint=cam.microlens_array.pitch * so / si, shape=shape)


def _lit_fraction(ux, uy, cell, radius, n=4):
    """Fraction of a cell × cell square centred at (ux, uy) inside the disc (n × n samples)."""
    o = (np.arange(n) - (n - 1) / 2) * (cell / n)
    frac = np.zeros(ux.shape)
    for a in o:
        for b in o:
            frac += (ux + a) ** 2 + (uy + b) ** 2 <= radius ** 2
    return frac / (n * n)


def perspective_view(image, lf: LightField, grid_index, u=(0.0, 0.0)) -> np.ndarray:
    """The sub-aperture image seen through aperture point ``u`` (metres).

    For each lenslet, the pixel whose aperture position is nearest to ``u`` (within half a
    cell); lenslets with none are NaN. Returns an array (lenslet rows, lenslet cols).
    """
    vals = lf.values(image).astype(float)
    d2 = ((lf.u - np.asarray(u, float)) ** 2).sum(axis=1)
    ok = d2 <= (0.75 * lf.cell) ** 2
    gi = np.asarray(grid_index, int)
    out = np.full((gi[:, 0].max() + 1, gi[:, 1].max() + 1), np.nan)
    best = np.full(len(gi), np.inf)
    k = lf.lenslet[ok]
    for kk, dd, vv in zip(k, d2[ok], vals[ok], strict=True):
        if dd < best[kk]:
            best[kk] = dd
            out[gi[kk, 0], gi[kk, 1]] = vv
    return out


def refocus(image, lf: LightField, alpha: float, *, pitch: float, shape_lenslets) -> np.ndarray:
    """Refocused image on a synthetic lenslet plane at α S_i (thesis §2.3, Ng 2005).

    Each ray meets the plane z = α S_i at s' = u + α (s - u); its value is splatted
    (bilinearly) onto a lenslet-pitch grid at s'/α (the magnification of the nominal plane
    is kept) and normalised by the splatted ray count.

    Parameters
    ----------
    alpha : float
        α > 1 focuses in front of the nominal focal plane, α < 1 behind it.
    pitch : float
        Output grid spacing on the lenslet plane, metres.
    shape_lenslets : (rows, cols)
        Output shape; the grid is centred on the optical axis.
    """
    if not alpha > 0:
        raise ValueError(f"alpha = {alpha!r}: expected > 0")
    vals = lf.values(image).astype(float)
    # the aperture point u lives on the lens plane; at the lenslet plane the ray has moved
    # from u (z = 0) to s (z = S_i): at z = α S_i it is at u + α (s - u)
    sp = (lf.u + alpha * (lf.s - lf.u)) / alpha
    rows, cols = shape_lenslets
    fc = sp[:, 0] / pitch + (cols - 1) / 2
    fr = sp[:, 1] / pitch + (rows - 1) / 2
    acc = np.zeros((rows + 1) * (cols + 1))
    wgt = np.zeros_like(acc)
    r0, c0 = np.floor(fr).astype(int), np.floor(fc).astype(int)
    ar, ac = fr - r0, fc - c0
    for drr, dcc, w in ((0, 0, (1 - ar) * (1 - ac)), (0, 1, (1 - ar) * ac),
                        (1, 0, ar * (1 - ac)), (1, 1, ar * ac)):
        rr, cc = r0 + drr, c0 + dcc
        ok = (rr >= 0) & (rr < rows) & (cc >= 0) & (cc < cols)
        idx = rr[ok] * (cols + 1) + cc[ok]
        np.add.at(acc, idx, (w * vals)[ok])
        np.add.at(wgt, idx, w[ok])
    out = np.where(wgt > 0, acc / np.where(wgt > 0, wgt, 1), np.nan)
    return out.reshape(rows + 1, cols + 1)[:rows, :cols]
