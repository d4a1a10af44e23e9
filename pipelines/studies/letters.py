"""Light field on a real plenoptic 1.0 image: the plenoptomos "letters" data set.

The data (``shared/data/plenoptomos_letters_ULF``, from cicwi/plenoptomos, GPL-3.0; never copied
into this repository) are a raw lenslet image of printed letters, a white (flat-field) image
and a dark frame from a camera with a Thorlabs MLA300-14AR-M (square, 300 µm pitch,
f_l = 18.6 mm, 18.6 mm in front of a 6.45 µm sensor) behind a 200 mm lens. The study:

1. calibrates the camera from the white image alone:
   :func:`~plenopiv.calibration.spots.detect_spots` and
   :func:`~plenopiv.calibration.spots.fit_lattice` give the micro-image centres (the focal
   spots x_c), their pitch gives S from the focal-point relation p = k d, k = 1 + f̄/S
   (thesis Eq. 3.11), and the lenslet centres follow as d = p/k about the optical axis;
2. builds the light field (:func:`~plenopiv.lightfield.light_field`) of the image through
   the preprocess stage (:func:`preprocessed_image`: dark subtracted, hot pixels repaired,
   the white's flat field) and its perspective views, and measures the parallax between
   views;
3. refocuses over α (:func:`~plenopiv.lightfield.refocus`) and finds the α of the sharpest
   letters, which the source's example puts at its α = 0.95.

Conventions: α here is plenopiv's (synthetic lenslet plane at α S_i, α > 1 in front of the
nominal focal plane). The source's α is an object-space ratio (refocus distance over the
focused distance z0, its "cone" geometry, with its own nominal camera, S = z1 = 400 mm): see
:func:`source_alpha` for the mapping, through the one quantity both describe, the parallax in
lenslets per sensor pixel of the micro-image.

Stage functions take arrays and return arrays or small frozen results;
:func:`pipelines.studies.letters_report.run` runs them and does the I/O (PNG figures, JSON and
Markdown summary).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage as ndi

from pipelines.studies.letters_data import DATA_NAME, LettersData
from plenopiv.calibration.lattice_fit import fit_lattice
from plenopiv.calibration.lenslets import micro_image_diameter as _micro_image_diameter
from plenopiv.calibration.model import Calibration
from plenopiv.calibration.spot_detection import detect_spots
from plenopiv.calibration.spot_types import Lattice, SpotFlag
from plenopiv.camera.model import camera_from_dict
from plenopiv.conventions import pixel_to_sensor, sensor_to_pixel
from plenopiv.errors import CalibrationError
from plenopiv.lightfield import LightField, light_field, perspective_view, refocus
from plenopiv.preprocess import master_dark, micro_images, prepare_frames, prepare_image

#: Lattice rows and columns (of this calibration's grid index) holding the two "ab" words,
#: clear of the page edges at columns ~7 and ~21, which lie at other depths.
LETTERS_ROI = (slice(2, 18), slice(8, 17))

#: The refocusing value of the source's example (its α, "cone" geometry).
SOURCE_ALPHA = 0.95

#: Default α sweep (plenopiv's α).
ALPHAS = tuple(np.round(np.arange(0.85, 1.10 + 1e-9, 0.005), 4))


def preprocessed_image(data: LettersData, wcal: WhiteCalibration) -> tuple[np.ndarray, dict]:
    """The raw image through the preprocess stage, as ``[preprocess]`` dark and white would.

    :func:`~plenopiv.preprocess.prepare_frames` with the master dark of the dark frame (its
    hot and cold pixels repaired), the white's flat field (each micro-image's throughput
    divided out, over the median plateau, so a typical micro-image keeps its counts) and
    ``hot_pixels = "auto"``, on the micro-images of the white calibration at the aperture its
    micro-images measure (``f_m`` over :attr:`WhiteCalibration.pupil_diameter`, f/25.8: the
    .ini's 6.6 mm stop, f/30.3, would model them 38 px across where they are 44.5 px, and
    leave the lit rims among the gaps the stage takes the black level and the noise from); then
    :func:`~plenopiv.preprocess.prepare_image`. The pixels the stage masks (gaps between
    micro-images, the rims below 0.2 of the white's plateau, dark micro-images) are NaN:
    the light-field code leaves them out.

    Returns ``(image, figures)``: counts of the dark subtracted, flat-fielded image, float64;
    what the stage found and did (bad pixels, masked pixels, the flat's figures).
    """
    f_number = data.optics["main_focal_length"] / wcal.pupil_diameter
    micro = micro_images(wcal.calibration, f_number=f_number)
    frames = prepare_frames(micro, dark=master_dark(data.dark, name="letters dark"),
                            white=data.white, hot_pixels="auto",
                            names={"dark": "letters dark", "white": "letters white"})
    prep = prepare_image(data.raw, frames, name="letters image")
    img = prep.image.copy()
    if prep.mask is not None:
        img[prep.mask] = np.nan
    figures = {**prep.figures, **frames.counts, "flat": frames.flat.to_dict(),
               "f_number": f_number, "micro_image_radius_px": micro.radius_px}
    return img, figures


def camera_config(optics: dict, shape, lattice_shape, *, image_distance: float,
                  rotation: float = 0.0, f_number: float | None = None) -> dict:
    """Camera config (TOML schema, DESIGN.md §7) for the letters camera.

    Parameters
    ----------
    optics : dict
        From :func:`read_optics`.
    shape : (rows, cols)
        The recorded image's shape, px (a crop of the declared sensor).
    lattice_shape : (rows, cols)
        Lenslets seen (complete or partial); the array must fit on the sensor.
    image_distance : float
        Effective S_i, metres.
    rotation : float
        MLA rotation, radians.
    f_number : float, optional
        Default: main focal length over the .ini's aperture diameter.
    """
    um, mm = 1e6, 1e3
    n = f_number or optics["main_focal_length"] / optics["aperture_diameter"]
    return {
        "name": "plenoptomos letters camera (Thorlabs MLA300-14AR-M, 200 mm lens)",
        "sensor": {"rows": int(shape[0]), "cols": int(shape[1]),
                   "pixel_pitch_um": optics["pixel_pitch"] * um},
        "microlens_array": {"rows": int(lattice_shape[0]), "cols": int(lattice_shape[1]),
                            "pitch_um": optics["mla_pitch"] * um,
                            "focal_length_um": optics["lenslet_focal_length"] * um,
                            "sensor_distance_um": optics["sensor_distance"] * um,
                            "grid": "square", "rotation_rad": float(rotation)},
        "main_lens": {"focal_length_mm": optics["main_focal_length"] * mm, "f_number": float(n),
                      "image_distance_mm": image_distance * mm},
    }


# --------------------------------------------------------------------------------------------
# Calibration from the white image
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class WhiteCalibration:
    """What the white image says about the camera.

    Attributes
    ----------
    calibration : Calibration
        Method "white image": focal spots from the fitted lattice, lenslet centres d = p/k.
    lattice : Lattice
        The micro-image lattice.
    pitch_px : (2,) float
        Micro-image pitch (rows, cols), px.
    scale : float
        k = mean pitch · p_p / p_m = 1 + f̄/S.
    image_distance : float
        S = f̄/(k - 1), metres (used).
    image_distance_nominal : float
        The .ini's lens-to-MLA distance, metres.
    disc_diameter_px : float
        Mean micro-image diameter (area above half the plateau), px.
    pupil_diameter : float
        Pupil diameter that makes micro-images that size, ``disc · p_p / (k - 1)``, metres.
    """

    calibration: Calibration
    lattice: Lattice
    pitch_px: np.ndarray
    scale: float
    image_distance: float
    image_distance_nominal: float
    disc_diameter_px: float
    pupil_diameter: float
    extra: dict = field(default_factory=dict)


def micro_image_diameter(white, spots_px, pitch_px: float) -> float:
    """Mean diameter (px) of the bright micro-images.

    :func:`plenopiv.calibration.spots.micro_image_diameter` of the white image.
    """
    return _micro_image_diameter(white, spots_px, pitch_px)


def calibrate_white(data: LettersData) -> WhiteCalibration:
    """Calibrate the letters camera from its dark-subtracted white image.

    Notes
    -----
    The white image is taken through the main lens at its working aperture, so each
    micro-image is the image of the pupil; its centre is the focal spot x_c (u = 0). With no
    alignment image, the lenslet centres follow from the focal-point relation (Eq. 3.11,
    "physical" back side, no substrate) ``p = k d``, ``k = 1 + f̄/S``, about the optical axis,
    taken at the centre of the recorded image (the PNG is a 1280 × 960 crop of the declared
    1388 × 1038 sensor; the axis's true position only shifts every d by the same
    (1 - 1/k) a, a few µm). k comes from the measured pitch: ``k = pitch_px p_p / p_m``.
    The focal spots are the fitted regular lattice (rms residual < 0.1 px), which also places
    the partial lenslets at the borders.
    """
    opt = data.optics
    white = np.clip(data.white - data.dark, 0.0, None)
    spots = detect_spots(white, grid="square")
    lat = fit_lattice(spots, grid="square", image_shape=white.shape)
    pitch = np.asarray(lat.pitch_px, float)
    pp, pm, fbar = opt["pixel_pitch"], opt["mla_pitch"], opt["sensor_distance"]
    k = float(np.mean(pitch)) * pp / pm
    if not k > 1.0:
        raise CalibrationError(f"micro-image pitch {np.mean(pitch):.4g} px is not larger than "
                               f"the lenslet pitch {pm / pp:.4g} px: k = {k:.5f}, expected > 1")
    s_pitch = fbar / (k - 1.0)
    index = lat.grid_index
    focal = lat.predict(index)
    centres = sensor_to_pixel(pixel_to_sensor(focal, white.shape, pp) / k, white.shape, pp)
    cfg = camera_config(opt, white.shape, lat.shape, image_distance=s_pitch,
                        rotation=lat.rotation_rad)
    camera = camera_from_dict(cfg, source="plenoptomos letters .ini + white image")
    complete = (lat.flags & SpotFlag.EDGE) == 0
    disc = micro_image_diameter(white, focal[complete], float(np.mean(pitch)))
    cal = Calibration(camera=camera.with_image_distance(s_pitch), centre_px=centres,
                      focal_spot_px=focal, grid_index=index, method="white image",
                      rotation=lat.rotation_rad, rms_residual_px=lat.rms_residual_px,
                      extra={"pitch_px": pitch.tolist(), "k": k,
                             "image_distance_nominal_m": opt["mla_z"],
                             "micro_image_diameter_px": disc})
    return WhiteCalibration(calibration=cal, lattice=lat, pitch_px=pitch, scale=k,
                            image_distance=s_pitch, image_distance_nominal=opt["mla_z"],
                            disc_diameter_px=disc, pupil_diameter=disc * pp / (k - 1.0),
                            extra={"n_spots": int(len(index)),
                                   "n_complete": int(np.count_nonzero(complete))})


# --------------------------------------------------------------------------------------------
# α conventions
# --------------------------------------------------------------------------------------------


def source_alpha(alpha, *, image_distance: float, sensor_distance: float, pixel_pitch: float,
                 mla_pitch: float, micro_image_pitch_px: float, source_z1: float = 0.4,
                 source_f2: float = 18.6e-3, source_f1: float = 0.2):
    """Map plenopiv's α to the source's (plenoptomos "cone" α, object space).

    Parameters
    ----------
    alpha : float or ndarray
        plenopiv's α: synthetic lenslet plane at α S_i (image space).
    image_distance, sensor_distance : float
        This calibration's S_i and f̄, metres.
    pixel_pitch, mla_pitch : float
        p_p and the lenslet pitch p_m, metres.
    micro_image_pitch_px : float
        Micro-image pitch, px.
    source_z1, source_f2, source_f1 : float
        The source's lens-to-MLA distance, MLA-to-sensor distance and main focal length,
        metres (its .ini: 400 mm, 18.6 mm, 200 mm).

    Returns
    -------
    float or ndarray
        The source's α for the same refocus plane.

    Notes
    -----
    Both conventions shear the light field; what they share is the parallax D, lenslets of
    image shift per sensor pixel of position under the lenslet. plenopiv (``refocus``): a ray
    lands at s + u (1/α - 1) with u = -(x - x_c) S_i/f̄, so
    ``D = -(1 - 1/α) (S_i/f̄) (p_p/p_m)``. plenoptomos (``Camera.get_sheared_coords``, cone):
    a point at z = α z0 is seen from aperture point u at X/α + u (1 - 1/α) on the plane z0,
    with u = p_p z1/f2 per micro-image sample, ``n = ceil(pitch - 0.1)`` samples per
    micro-image pitch (its resampling), detector pixels of one micro-image pitch times
    M = z0/z1, z0 = z1 f1/(z1 - f1); it flips u and the image together, which leaves depths
    alone, so ``D = (1 - 1/α_src) (z1/f2) (p_p n/pitch_px) z1/(pitch_px p_p z0)``.
    """
    a = np.asarray(alpha, float)
    c_ours = image_distance / sensor_distance * pixel_pitch / mla_pitch
    n = math.ceil(micro_image_pitch_px - 0.1)
    z0 = source_z1 * source_f1 / (source_z1 - source_f1)
    c_src = (source_z1 / source_f2) * n / micro_image_pitch_px ** 2 * source_z1 / z0
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -(1.0 - 1.0 / a) * c_ours / c_src     # 1 - 1/α_src
        out = 1.0 / (1.0 - t)
    return float(out) if np.ndim(alpha) == 0 else out


def plenopiv_alpha(alpha_source, **geometry):
    """Inverse of :func:`source_alpha` (same keyword arguments)."""
    a = np.asarray(alpha_source, float)
    one = source_alpha(2.0, **geometry)          # (1 - 1/α_src) = -ratio (1 - 1/α); α = 2
    ratio = -(1.0 - 1.0 / one) / 0.5
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -(1.0 - 1.0 / a) / ratio
        out = 1.0 / (1.0 - t)
    return float(out) if np.ndim(alpha_source) == 0 else out


def alpha_geometry(wcal: WhiteCalibration, optics: dict) -> dict:
    """Collect the keyword arguments of :func:`source_alpha` for this calibration."""
    return {"image_distance": wcal.image_distance, "sensor_distance": optics["sensor_distance"],
            "pixel_pitch": optics["pixel_pitch"], "mla_pitch": optics["mla_pitch"],
            "micro_image_pitch_px": float(np.mean(wcal.pitch_px)),
            "source_z1": optics["mla_z"], "source_f2": optics["sensor_distance"],
            "source_f1": optics["main_focal_length"]}


def refocus_depth(alpha: float, *, image_distance: float, focal_length: float) -> dict:
    """Where plenopiv's α puts the refocus plane in this (thin-lens) camera.

    Returns image distance α S_i, object distance S_o' (1/S_o' = 1/f - 1/(α S_i)), the depth
    Z = S_o' - S_o from the nominal focal plane (negative: nearer the camera) and the
    object-space ratio S_o'/S_o, all in metres.
    """
    so = 1.0 / (1.0 / focal_length - 1.0 / image_distance)
    si2 = alpha * image_distance
    so2 = 1.0 / (1.0 / focal_length - 1.0 / si2)
    return {"image_distance": si2, "object_distance": so2, "depth": so2 - so,
            "object_ratio": so2 / so}


# --------------------------------------------------------------------------------------------
# Views, parallax, sharpness
# --------------------------------------------------------------------------------------------


def _fill(img):
    v = np.asarray(img, float)
    return np.where(np.isfinite(v), v, np.nanmean(v))


def ncc(a, b, region=LETTERS_ROI) -> float:
    """Normalised cross-correlation of two views over ``region`` (NaN-free there)."""
    x = np.asarray(a, float)[region].ravel()
    y = np.asarray(b, float)[region].ravel()
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok] - x[ok].mean(), y[ok] - y[ok].mean()
    return float((x * y).sum() / math.sqrt((x * x).sum() * (y * y).sum()))


def register_shift(reference, moved, region=LETTERS_ROI, *, iterations: int = 30):
    """Sub-lenslet shift of ``moved`` against ``reference`` over ``region``.

    Returns ``d = (d_row, d_col)`` (lattice units) such that
    ``reference(x) ≈ g moved(x + d) + o`` (gain g and offset o fitted too): the content of
    ``moved`` sits at ``+d``. Gauss-Newton (Lucas-Kanade) on cubic-spline shifts; NaN in
    ``moved`` is filled with its mean, so keep ``region`` inside the valid lenslets.
    """
    a = np.asarray(reference, float)[region]
    b = _fill(moved)
    d = np.zeros(2)
    for _ in range(iterations):
        bs = ndi.shift(b, -d, order=3, mode="nearest")
        gy, gx = np.gradient(bs)
        x = np.column_stack([bs[region].ravel(), np.ones(a.size), gy[region].ravel(),
                             gx[region].ravel()])
        ok = np.isfinite(a.ravel())
        coef, *_ = np.linalg.lstsq(x[ok], a.ravel()[ok], rcond=None)
        step = coef[2:] / coef[0]
        d = d + step
        if np.abs(step).max() < 1e-5:
            break
    return d


@dataclass(frozen=True)
class Parallax:
    """Shift of the letters between perspective views along x and y.

    Attributes
    ----------
    u : (n,) float
        Aperture positions along the axis, metres.
    shift_x, shift_y : (n,) float
        Column shift for views at (u, 0), row shift for views at (0, u), lenslets, against the
        central view.
    slope : (2,) float
        Fitted ds/du along x and y (dimensionless: metres on the lenslet plane per metre of u).
    alpha : (2,) float
        plenopiv's α at which these views align: 1/(1 - ds/du) (a view's content sits at
        s_ref - u (1/α - 1)).
    """

    u: np.ndarray
    shift_x: np.ndarray
    shift_y: np.ndarray
    slope: np.ndarray
    alpha: np.ndarray

    @property
    def alpha_mean(self) -> float:
        """Mean of the x and y estimates."""
        return float(np.mean(self.alpha))


def parallax(image, lf: LightField, grid_index, *, region=LETTERS_ROI, n: int = 9,
             extent: float = 0.8) -> Parallax:
    """Measure the letters' parallax between linear-interpolated perspective views.

    Parameters
    ----------
    image : ndarray
        Flat-fielded raw image.
    lf : LightField
    grid_index : (N, 2) int
    region : tuple of slices
        Lattice region to register.
    n : int
        Views along each axis, at u from ``-extent R`` to ``extent R`` (R: aperture radius).
    extent : float
        Fraction of the aperture radius.
    """
    us = np.linspace(-extent, extent, n) * lf.aperture_radius
    ref = perspective_view(image, lf, grid_index, (0.0, 0.0), interpolation="linear")
    sx = np.array([register_shift(ref, perspective_view(image, lf, grid_index, (u, 0.0),
                                                        interpolation="linear"), region)[1]
                   for u in us])
    sy = np.array([register_shift(ref, perspective_view(image, lf, grid_index, (0.0, u),
                                                        interpolation="linear"), region)[0]
                   for u in us])
    pitch = _lattice_pitch(lf, grid_index)
    slope = np.array([np.polyfit(us, sx, 1)[0] * pitch[1], np.polyfit(us, sy, 1)[0] * pitch[0]])
    return Parallax(u=us, shift_x=sx, shift_y=sy, slope=slope, alpha=1.0 / (1.0 - slope))


def _lattice_pitch(lf: LightField, grid_index) -> np.ndarray:
    """Lenslet-centre pitch (rows, cols), metres, fitted to the rays' lenslet centres."""
    gi = np.asarray(grid_index, int)
    s = _centres(lf, len(gi))
    ok = np.isfinite(s[:, 0])
    x = np.column_stack([np.ones(ok.sum()), gi[ok, 0], gi[ok, 1]])
    coef, *_ = np.linalg.lstsq(x, s[ok], rcond=None)
    return np.array([np.hypot(*coef[1]), np.hypot(*coef[2])])


def _centres(lf: LightField, n: int) -> np.ndarray:
    cnt = np.bincount(lf.lenslet, minlength=n).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.stack([np.bincount(lf.lenslet, lf.s[:, i], minlength=n) / cnt
                         for i in (0, 1)], axis=1)


MEASURES = ("gradient", "laplacian")


def sharpness(img, region=None, *, measure: str = "gradient") -> float:
    """Focus measure of an image where it is valid.

    Parameters
    ----------
    img : ndarray
        Refocused image (NaN: no data).
    region : tuple of slices, optional
        Where to evaluate (default everywhere).
    measure : {"gradient", "laplacian"}
        ``"gradient"``: normalised gradient energy mean(|∇I|²)/mean(I)² (central differences);
        ``"laplacian"``: variance of the 5-point Laplacian over mean(I)². Evaluated on pixels
        whose 3 × 3 neighbourhood is valid and inside ``region``.
    """
    if measure not in MEASURES:
        raise ValueError(f"measure = {measure!r}: expected one of {MEASURES}")
    im = np.asarray(img, float)
    valid = np.isfinite(im)
    if region is not None:
        inside = np.zeros_like(valid)
        inside[region] = True
        valid &= inside
    core = ndi.binary_erosion(valid, np.ones((3, 3)), border_value=0)
    if core.sum() < 4:
        raise ValueError("sharpness: fewer than 4 valid pixels in the region")
    f = np.where(np.isfinite(im), im, 0.0)
    mean = f[core].mean()
    if measure == "gradient":
        gy, gx = np.gradient(f)
        return float((gx[core] ** 2 + gy[core] ** 2).mean() / mean ** 2)
    lap = ndi.laplace(f)
    return float(lap[core].var() / mean ** 2)


def peak_alpha(alphas, values) -> float:
    """α of the maximum, refined by a parabola through the three points around it."""
    a = np.asarray(alphas, float)
    v = np.asarray(values, float)
    i = int(np.argmax(v))
    if 0 < i < len(v) - 1:
        c2, c1, _ = np.polyfit(a[i - 1:i + 2] - a[i], v[i - 1:i + 2], 2)
        if c2 < 0:
            return float(a[i] - c1 / (2 * c2))
    return float(a[i])


def splat_region(lf: LightField, grid_index, region, shape) -> tuple:
    """Map a lattice ``region`` onto the grid of ``refocus(method="splat")``.

    Returns the slices of the axis-centred lenslet-pitch grid that cover the region.
    """
    gi = np.asarray(grid_index, int)
    s = _centres(lf, len(gi))
    ok = np.isfinite(s[:, 0])
    x = np.column_stack([np.ones(ok.sum()), gi[ok, 0], gi[ok, 1]])
    coef, *_ = np.linalg.lstsq(x, s[ok], rcond=None)
    pitch = _lattice_pitch(lf, gi)
    corners = np.array([[region[0].start, region[1].start],
                        [region[0].stop - 1, region[1].stop - 1]], float)
    xy = coef[0] + corners[:, :1] * coef[1] + corners[:, 1:] * coef[2]
    col = xy[:, 0] / pitch[1] + (shape[1] - 1) / 2
    row = xy[:, 1] / pitch[0] + (shape[0] - 1) / 2
    r0, r1 = int(round(row.min())), int(round(row.max())) + 1
    c0, c1 = int(round(col.min())), int(round(col.max())) + 1
    return (slice(max(r0, 0), min(r1, shape[0])), slice(max(c0, 0), min(c1, shape[1])))


def focus_sweep(image, lf: LightField, grid_index, alphas=ALPHAS, *, region=LETTERS_ROI,
                method: str = "fourier") -> dict:
    """Measure the sharpness of the refocused image over α.

    ``method`` is :func:`~plenopiv.lightfield.refocus`'s, "fourier" (default) or "splat".

    Returns
    -------
    dict
        ``alpha`` (plenopiv's), ``gradient`` and ``laplacian`` (see :func:`sharpness`) over
        ``region`` and ``gradient_all`` over the whole valid image, and the ``peak`` α of each.
        With ``method="splat"`` the image is on the axis-centred lenslet-pitch grid and the
        region is mapped onto it.
    """
    if method not in ("fourier", "splat"):
        raise ValueError(f"method = {method!r}: expected 'fourier' or 'splat'")
    gi = np.asarray(grid_index, int)
    shape = (int(gi[:, 0].max()) + 1, int(gi[:, 1].max()) + 1)
    pitch = _lattice_pitch(lf, gi)
    reg = region if method == "fourier" else splat_region(lf, gi, region, shape)
    out = {"alpha": [], "gradient": [], "laplacian": [], "gradient_all": []}
    for a in alphas:
        if method == "fourier":
            img = refocus(image, lf, float(a), method="fourier", grid_index=gi)
        else:
            img = refocus(image, lf, float(a), pitch=float(np.mean(pitch)), shape_lenslets=shape)
        out["alpha"].append(float(a))
        out["gradient"].append(sharpness(img, reg))
        out["laplacian"].append(sharpness(img, reg, measure="laplacian"))
        out["gradient_all"].append(sharpness(img))
    out["peak"] = {k: peak_alpha(out["alpha"], out[k])
                   for k in ("gradient", "laplacian", "gradient_all")}
    return out


# --------------------------------------------------------------------------------------------
# The study
# --------------------------------------------------------------------------------------------


def analyse(data: LettersData, *, alphas=ALPHAS, with_splat: bool = True) -> dict:
    """Calibrate, build the light field, views, parallax and focus sweeps (no I/O).

    Returns a dict of arrays and numbers; :func:`pipelines.studies.letters_report.run` turns it
    into files.
    """
    wcal = calibrate_white(data)
    cal = wcal.calibration
    lf = light_field(cal)
    gi = cal.grid_index
    img, prep = preprocessed_image(data, wcal)
    r = lf.aperture_radius
    view_u = {"centre": (0.0, 0.0), "left": (-0.7 * r, 0.0), "right": (0.7 * r, 0.0),
              "top": (0.0, -0.7 * r), "bottom": (0.0, 0.7 * r)}
    views = {k: perspective_view(img, lf, gi, u, interpolation="linear")
             for k, u in view_u.items()}
    par = parallax(img, lf, gi)
    sweep = focus_sweep(img, lf, gi, alphas)
    splat = focus_sweep(img, lf, gi, alphas, method="splat") if with_splat else None
    geo = alpha_geometry(wcal, data.optics)
    peak = sweep["peak"]["gradient"]
    return {"wcal": wcal, "lf": lf, "image": img, "preprocess": prep, "views": views,
            "view_u": view_u,
            "parallax": par, "sweep": sweep, "splat": splat, "geometry": geo, "peak": peak,
            "lattice_pitch": _lattice_pitch(lf, gi)}


def summary(res: dict, optics: dict) -> dict:
    """JSON-ready numbers of an :func:`analyse` result."""
    wcal, lf, par, sweep, geo = (res[k] for k in ("wcal", "lf", "parallax", "sweep",
                                                   "geometry"))
    cam = wcal.calibration.camera
    f = optics["main_focal_length"]
    nominal_geo = dict(geo, image_distance=wcal.image_distance_nominal)
    peak = sweep["peak"]["gradient"]
    views = res["views"]
    c = views["centre"]

    def at(alpha):
        d = refocus_depth(alpha, image_distance=wcal.image_distance, focal_length=f)
        return {"alpha": alpha, "alpha_source": source_alpha(alpha, **geo),
                "refocus_image_distance_mm": d["image_distance"] * 1e3,
                "object_distance_mm": d["object_distance"] * 1e3, "depth_mm": d["depth"] * 1e3}

    out = {
        "data": DATA_NAME,
        "image_shape": list(res["image"].shape),
        "calibration": {
            "grid": wcal.lattice.grid, "pitch_px": wcal.pitch_px.tolist(),
            "pitch_std_px": np.asarray(wcal.lattice.pitch_std_px).tolist(),
            "rotation_rad": wcal.lattice.rotation_rad,
            "rms_residual_px": wcal.lattice.rms_residual_px,
            "lattice_shape": list(wcal.lattice.shape), "n_spots": wcal.extra["n_spots"],
            "n_complete": wcal.extra["n_complete"], "k": wcal.scale,
            "image_distance_from_pitch_mm": wcal.image_distance * 1e3,
            "image_distance_nominal_mm": wcal.image_distance_nominal * 1e3,
            "pitch_px_if_nominal": optics["mla_pitch"] / optics["pixel_pitch"]
            * (1 + optics["sensor_distance"] / wcal.image_distance_nominal),
            "micro_image_diameter_px": wcal.disc_diameter_px,
            "micro_image_diameter_px_if_6p6mm_stop": optics["aperture_diameter"]
            * (wcal.scale - 1) / optics["pixel_pitch"],
            "pupil_diameter_from_micro_images_mm": wcal.pupil_diameter * 1e3,
            "f_number_used": cam.main_lens.f_number,
        },
        "preprocess": res["preprocess"],
        "light_field": {"n_rays": lf.n_rays, "aperture_radius_mm": lf.aperture_radius * 1e3,
                        "cell_um": lf.cell * 1e6, "views_shape": list(c.shape)},
        "views": {
            "u_mm": {k: [v * 1e3 for v in u] for k, u in res["view_u"].items()},
            "roi": [[LETTERS_ROI[0].start, LETTERS_ROI[0].stop],
                    [LETTERS_ROI[1].start, LETTERS_ROI[1].stop]],
            "centre_std_roi": float(np.nanstd(c[LETTERS_ROI])),
            "ncc_with_centre": {k: ncc(c, v) for k, v in views.items() if k != "centre"},
        },
        "parallax": {"u_mm": (par.u * 1e3).tolist(), "shift_x_lenslets": par.shift_x.tolist(),
                     "shift_y_lenslets": par.shift_y.tolist(), "slope": par.slope.tolist(),
                     "alpha": par.alpha.tolist(), "alpha_mean": par.alpha_mean,
                     "alpha_source": source_alpha(par.alpha_mean, **geo)},
        "focus": {
            "method": "fourier",
            "alpha": sweep["alpha"],
            "gradient": sweep["gradient"], "laplacian": sweep["laplacian"],
            "gradient_all": sweep["gradient_all"],
            "alpha_source": [source_alpha(a, **geo) for a in sweep["alpha"]],
            "peak": sweep["peak"],
            "peak_alpha_source": {k: source_alpha(v, **geo) for k, v in sweep["peak"].items()},
            "peak_alpha_if_nominal_S": plenopiv_alpha(source_alpha(peak, **geo), **nominal_geo),
            "source_alpha": SOURCE_ALPHA,
            "source_alpha_in_plenopiv": plenopiv_alpha(SOURCE_ALPHA, **geo),
            "peak_plane": at(peak),
            "source_plane": at(plenopiv_alpha(SOURCE_ALPHA, **geo)),
        },
    }
    if res["splat"] is not None:
        s = res["splat"]
        out["focus_splat"] = {"alpha": s["alpha"], "gradient": s["gradient"], "peak": s["peak"]}
    return out


def refocused_planes(res: dict) -> list[tuple[str, np.ndarray]]:
    """Fourier refocus of the flat-fielded image at five α: ``(title, image)`` pairs.

    α = 0.95, 1 (nominal), the focus-sweep peak, the source's 0.95 in plenopiv's α, and 1.08.
    """
    peak, geo = res["peak"], res["geometry"]
    src_in = plenopiv_alpha(SOURCE_ALPHA, **geo)
    lf, gi = res["lf"], res["wcal"].calibration.grid_index
    show = [(0.95, "α = 0.95"), (1.0, "α = 1 (nominal)"), (peak, f"peak α = {peak:.4f}"),
            (src_in, f"source's 0.95 (α = {src_in:.4f})"), (1.08, "α = 1.08")]
    return [(title, refocus(res["image"], lf, al, method="fourier", grid_index=gi))
            for al, title in show]

