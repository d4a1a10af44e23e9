"""The light field: every lit pixel of a calibrated camera as a ray (s, t, u, v).

:func:`light_field` turns a :class:`~plenopiv.calibration.model.Calibration` into a
:class:`LightField`: per lit pixel its aperture-plane position u = -(x - x_c) · S_i,eff / f̄,
its lenslet centre s and the lenslet's conjugate X_f = s/M on the nominal focal plane
(docs/design.md §4, thesis Eqs. 4.1/4.5), in effective coordinates, metres. Pixels whose aperture
cell lies mostly outside the aperture disc receive no light and are left out.

See docs/methods.md#rays.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings
from dataclasses import dataclass

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.camera.resolution import MICRO_IMAGE_TOLERANCE
from plenopiv.conventions import pixel_to_sensor
from plenopiv.errors import CalibrationError, PlenopivWarning
from plenopiv.lightfield import _kernels as _lk


class LightFieldWarning(PlenopivWarning):
    """The light field's model does not match its calibration (micro-image size, rays)."""


# fewer rays per lenslet than this on average: the light field is nearly empty
MIN_RAYS_PER_LENSLET = 4.0


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

    @functools.cached_property
    def focal_plane_position(self) -> np.ndarray:
        """X_f = s/M, the ray's point on the nominal focal plane (P, 2), metres.

        Computed on first use and kept (read-only): the projectors, the in-view checks and the
        tracking read it many times per reconstruction (16 bytes per ray).
        """
        xf = self.s / self.magnification
        xf.flags.writeable = False
        return xf

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

    def subset(self, keep) -> LightField:
        """Some rays, as a light field of the same camera.

        ``keep``: a (P,) bool mask, or indices of rays (in the order the subset is to have).
        """
        keep = np.asarray(keep)
        if keep.dtype == bool and keep.shape != (self.n_rays,):
            raise ValueError(f"keep has shape {keep.shape}; expected ({self.n_rays},)")
        if keep.dtype != bool and (keep.ndim != 1 or not np.issubdtype(keep.dtype, np.integer)):
            raise ValueError(f"keep must be a ({self.n_rays},) bool mask or 1-D ray indices; "
                             f"got {keep.dtype} of shape {keep.shape}")
        return dataclasses.replace(self, pixel=self.pixel[keep], lenslet=self.lenslet[keep],
                                   s=self.s[keep], u=self.u[keep], lit=self.lit[keep])

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
    # the messages name the key the f-number came from
    key = "[main_lens] f_number" if f_number is None else "[reconstruction] f_number"
    radius, r_img_px, pitch_px, r_max, half = _micro_image(calibration, n_f)
    cell = pp * si / fbar
    shape = cam.sensor.shape

    spots = np.asarray(calibration.focal_spot_px, float)
    centres_m = pixel_to_sensor(calibration.centre_px, shape, pp)
    _check_micro_images(calibration, n_f, 2.0 * r_img_px, pitch_px, key)
    # lenslet by lenslet in chunks: each chunk's working arrays stay below the allocator's
    # threshold for fresh pages, which a 16 MP sensor's whole arrays (20 million candidate
    # pixels) paid in page faults on every temporary
    parts = [_candidate_rays(spots[lo:lo + CHUNK_LENSLETS], lo, half, shape, r_max,
                             (pp, si, fbar), cell, radius, min_lit, edge_centroid)
             for lo in range(0, len(spots), CHUNK_LENSLETS)]
    columns = list(zip(*parts, strict=True)) or [np.zeros(0, np.int64)] * 2 + [np.zeros(0)] * 3
    pix, k_idx, ux, uy, lit = (np.concatenate(c) for c in columns)
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
            f"with {key} = {n_f:g} the modelled micro-images are {2 * r_img_px:.2f} px "
            "across; views and refocused images will be mostly blank or NaN (check it)",
            LightFieldWarning, stacklevel=2)
    return LightField(
        pixel=pix, lenslet=k_idx[order].astype(np.int32), s=centres_m[k_idx[order]],
        u=np.stack([ux[order], uy[order]], axis=1), lit=lit[order],
        image_distance=si, object_distance=so, aperture_radius=radius, cell=cell,
        footprint=cam.microlens_array.pitch * so / si, shape=shape)


#: Lenslets per chunk of :func:`light_field`'s candidate pixels.
CHUNK_LENSLETS = 2048


def _candidate_rays(spots, first: int, half: int, shape, r_max: float, optics: tuple,
                    cell: float, radius: float, min_lit: float, edge_centroid: bool) -> tuple:
    """The kept rays of some lenslets: ``(pixel, lenslet, ux, uy, lit)``, lenslet by lenslet.

    ``spots`` (rows, cols) are lenslets ``first, first + 1, ...``; ``optics``: the pixel
    pitch, S_i and f̄ (metres), which map a pixel's offset from its spot to the aperture.
    See :func:`light_field`.
    """
    pp, si, fbar = optics
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
    pix = rows[keep].astype(np.int64) * shape[1] + cols[keep]
    return pix, k_idx + first, ux[keep], uy[keep], lit[keep]


def _micro_image(calibration: Calibration, n_f: float) -> tuple:
    """``(radius, r_img_px, pitch_px, r_max, half)`` of :func:`light_field` at f-number ``n_f``.

    The aperture radius (m), the micro-image's radius and pitch (px), the radius within which
    a pixel belongs to its lenslet (within the aperture image, R f̄/S_i, and within half a
    micro-image pitch of its own spot, so that no pixel belongs to two lenslets) and the
    half-width of the square of candidate pixels about each spot.
    """
    cam = calibration.camera
    si = calibration.image_distance
    fbar = cam.microlens_array.sensor_distance
    radius = cam.main_lens.focal_length / n_f / 2
    if cam.microlens_array.back_side == "thesis" and cam.microlens_array.substrate is not None:
        # rays keep their in-glass angle behind the lenslets: the micro-images, and so the
        # aperture as the pixels see it through u = -(x - x_c) S_i/f̄, are n times smaller
        # (the depth scale this leaves is the internal correction, thesis Eq. 5.1)
        radius /= cam.microlens_array.substrate.refractive_index
    r_img_px = radius * fbar / si / cam.sensor.pixel_pitch
    pitch_px = cam.pitch_px * (1 + fbar / si)
    r_max = min(r_img_px + 1.0, 0.5 * pitch_px)
    return radius, r_img_px, pitch_px, r_max, int(math.ceil(r_max)) + 1


#: Peak bytes of :func:`light_field` per candidate pixel of one chunk (the square of pixels
#: about each focal spot that it examines, :data:`CHUNK_LENSLETS` lenslets at a time): its
#: index, offset, mask and float64 working arrays (traced peaks of 109 to 134 bytes on the
#: small camera and patches of both Auburn cameras, ``tracemalloc``).
BUILD_BYTES_PER_CANDIDATE = 140
#: Peak bytes per candidate pixel of the whole sensor once the kept rays are joined and
#: sorted (traced: 59 and 66 bytes for the two 16 MP cameras, whose peaks of 1.44 and 1.62
#: GB were 2.67 and 2.78 GB when the light field was built in one piece), and while the
#: chunks run (the rays kept so far, 40 bytes each, under half of the candidates).
KEPT_BYTES_PER_CANDIDATE = 70
CHUNKING_BYTES_PER_CANDIDATE = 20


def light_field_build_bytes(calibration: Calibration, *, f_number: float | None = None
                            ) -> float:
    """Peak memory of building the light field of ``calibration``, bytes, without building it.

    What a memory budget checks before :func:`light_field` allocates its working arrays.
    """
    cam = calibration.camera
    n_f = cam.main_lens.f_number if f_number is None else f_number
    half = _micro_image(calibration, n_f)[4]
    n_lenslets = len(np.asarray(calibration.focal_spot_px))
    candidates = n_lenslets * (2 * half + 1) ** 2
    chunk = min(n_lenslets, CHUNK_LENSLETS) * (2 * half + 1) ** 2
    return float(max(BUILD_BYTES_PER_CANDIDATE * chunk
                     + CHUNKING_BYTES_PER_CANDIDATE * candidates,
                     KEPT_BYTES_PER_CANDIDATE * candidates))


def _check_micro_images(calibration: Calibration, n_f: float, model_px: float,
                        pitch_px: float, key: str = "f_number") -> None:
    """Warn when the modelled micro-image size contradicts the calibration (see light_field)."""
    measured = calibration.extra.get("micro_image_diameter_px")
    if measured is not None and np.isfinite(measured) and measured > 0:
        ratio = model_px / float(measured)
        if not 1.0 / MICRO_IMAGE_TOLERANCE <= ratio <= MICRO_IMAGE_TOLERANCE:
            implied = n_f * ratio
            warnings.warn(
                f"{key} = {n_f:g} makes the micro-images {model_px:.1f} px across, but the "
                f"white image of the calibration shows {float(measured):.1f} px (as from "
                f"f_number = {implied:.3g}); the light field takes each lenslet's pixels "
                f"within the modelled size, so it {'misses' if ratio < 1 else 'adds dark'} "
                f"pixels: set {key} to the recording's aperture",
                LightFieldWarning, stacklevel=3)
            return
    if model_px > MICRO_IMAGE_TOLERANCE * pitch_px:
        warnings.warn(
            f"{key} = {n_f:g} makes the micro-images {model_px:.1f} px across, more than "
            f"their pitch {pitch_px:.1f} px: they would overlap, and each lenslet keeps only "
            "the pixels within half a pitch (check it)", LightFieldWarning, stacklevel=3)


def _lit_inside(ux, uy, inside, cell, radius):
    """:func:`~plenopiv.lightfield._kernels.lit_fraction` of the pixels ``inside``, 0 elsewhere."""
    out = [np.zeros(ux.shape) for _ in range(3)]
    for full, part in zip(out, _lk.lit_fraction(ux[inside], uy[inside], cell, radius, 8),
                          strict=True):
        full[inside] = part
    return out
