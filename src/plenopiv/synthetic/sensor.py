"""What a real recording adds to the ideal render: the sensor, the lenslets and the light.

:class:`RecordingSettings` describes the optics (lenslet throughput, vignetting), the light
(glow, particle brightness, a sheet's depth profile, the second pulse's energy) and the
sensor (black level and its fixed pattern, read noise, gain, ADC bits, hot and dead pixels);
its defaults are the ideal render and :data:`REALISTIC` is a typical set. One physical
camera's randomness is drawn once from a camera seed (:func:`camera_instance`), apart from
each frame's noise, so a dark, a white and a particle frame of one camera share it. Counts
are ADC numbers; lengths in millimetres. See docs/methods.md#a-real-recording.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field, StrictInt

from plenopiv._threads import run_slices
from plenopiv.camera.model import CameraModel
from plenopiv.camera.optics import focal_spot_exact, focal_spot_scale
from plenopiv.errors import ConfigError
from plenopiv.settings import settings

__all__ = ["REALISTIC", "SHEET_PROFILES", "CameraInstance", "RecordingSettings",
           "adc_full_scale", "camera_instance", "describe", "glow_field", "optical_gain",
           "particle_brightness", "particle_peak_irradiance", "record", "sheet_illumination",
           "vignetting_coefficient"]

SHEET_PROFILES = ("none", "gaussian", "tophat")

#: A hot pixel's dark signal is drawn once, uniform in this range times ``hot_pixel_counts``.
HOT_SPREAD = (0.5, 1.5)
#: Broad Gaussian blobs summed into the glow field.
GLOW_BLOBS = 3


@settings
class RecordingSettings:
    """The effects of a real recording on top of the ideal render; defaults: none.

    Sensor:

    black_level_counts : offset added to every pixel, counts.
    column_offset_counts, pixel_offset_counts : rms of the fixed pattern of the offset, one
        value per column and one per pixel, counts (fixed for a camera instance).
    read_noise_counts : rms read noise of every frame, counts.
    gain_counts_per_electron : counts per photo-electron; ``None`` (default): the ADC's full
        scale over ``full_well`` electrons (the full well fills the ADC).
    adc_bits : the ADC's bit depth, 8 to 16: counts saturate at 2^adc_bits - 1 (a 12-bit
        camera writes 0..4095 into 16-bit files). ``None``: the file's bit depth.
    hot_pixel_fraction : share of pixels with a large dark current.
    hot_pixel_counts : mean dark signal of a hot pixel per frame, counts; each hot pixel's
        own is drawn once, uniform in 0.5 to 1.5 times this.
    dead_pixel_fraction : share of pixels without response to light (they read the black
        level with its fixed pattern and read noise, like a dark pixel).

    Optics and light:

    throughput_spread : each lenslet passes a factor drawn once, uniform in
        1 ± throughput_spread, of the light.
    vignetting : fraction of the light lost at the rim of a micro-image; the gain falls as
        ``(1 + a ρ²)^-2`` (cos⁴-like) with ρ the distance from the centre of the fall-off over
        half the pitch (of the micro-images, or of the lenslets), and goes on falling beyond
        the rim.
    vignetting_centre : "micro-image" (default: the fall-off is centred on each micro-image,
        where the chief ray from the exit pupil through the lenslet's centre lands) |
        "lenslet" (centred on the lenslet's axis, the point under its centre: a response
        that falls with the angle of the light through the lenslet, which dims the outer
        side of a micro-image off the main lens's axis and pulls a focal spot's centroid
        towards its lenslet's axis).
    glow : a smooth additive background light, its peak this fraction of the irradiance of an
        in-focus particle of unit brightness (:func:`particle_peak_irradiance`); particle
        images only, fixed for a camera instance (the set-up), scaled by the pulse energy.
    brightness_sigma_ln : particle brightness is log-normal with median 1 and this standard
        deviation of its logarithm (0: all equal).
    sheet_profile : "none" (uniform light) | "gaussian" (full width at half maximum
        sheet_thickness_mm) | "tophat" (full width sheet_thickness_mm, dark outside).
    sheet_centre_mm, sheet_thickness_mm : the sheet's centre Z (mm, from the nominal focal
        plane, + away from the camera) and thickness (mm).
    pulse_ratio : energy of the second pulse of a pair over the first's.
    """

    black_level_counts: float = Field(0.0, ge=0, le=65535)
    column_offset_counts: float = Field(0.0, ge=0, le=1000)
    pixel_offset_counts: float = Field(0.0, ge=0, le=1000)
    read_noise_counts: float = Field(0.0, ge=0, le=1000)
    gain_counts_per_electron: float | None = Field(None, gt=0, le=1000)
    adc_bits: StrictInt | None = Field(None, ge=8, le=16)
    hot_pixel_fraction: float = Field(0.0, ge=0, le=0.1)
    hot_pixel_counts: float = Field(1000.0, gt=0, le=65535)
    dead_pixel_fraction: float = Field(0.0, ge=0, le=0.1)
    throughput_spread: float = Field(0.0, ge=0, lt=1)
    vignetting: float = Field(0.0, ge=0, lt=1)
    vignetting_centre: Literal["micro-image", "lenslet"] = "micro-image"
    glow: float = Field(0.0, ge=0, le=100)
    brightness_sigma_ln: float = Field(0.0, ge=0, le=3)
    sheet_profile: Literal["none", "gaussian", "tophat"] = "none"
    sheet_centre_mm: float = Field(0.0, ge=-1e4, le=1e4)
    sheet_thickness_mm: float = Field(10.0, gt=0, le=1e4)
    pulse_ratio: float = Field(1.0, gt=0, le=100)

    @property
    def is_ideal(self) -> bool:
        """Every effect off: renders are those of the ideal simulator, bit for bit."""
        return self == RecordingSettings()

    @property
    def has_sensor(self) -> bool:
        """Any sensor effect on: the image is recorded by :func:`record`."""
        return (self.black_level_counts > 0 or self.column_offset_counts > 0
                or self.pixel_offset_counts > 0 or self.read_noise_counts > 0
                or self.gain_counts_per_electron is not None or self.adc_bits is not None
                or self.hot_pixel_fraction > 0 or self.dead_pixel_fraction > 0)

    @property
    def has_optics(self) -> bool:
        """A lenslet throughput spread or a micro-image vignetting."""
        return self.throughput_spread > 0 or self.vignetting > 0


#: A typical real recording: black level 100 counts with a 3-count fixed pattern (1.5 per
#: column, 2.6 per pixel), read noise 3 counts, a 12-bit ADC, 1e-4 hot pixels (1000 counts
#: of dark signal), 1e-5 dead pixels, ±10 % lenslet throughput, 20 % vignetting at the rim
#: of a micro-image, a glow of 2 % of a particle's peak, particle brightness σ_ln 0.3, a
#: second pulse of 0.85 times the first's energy. The depth profile stays uniform: a sheet
#: is the experiment's, give it explicitly.
REALISTIC = RecordingSettings(
    black_level_counts=100.0, column_offset_counts=1.5, pixel_offset_counts=2.6,
    read_noise_counts=3.0, adc_bits=12, hot_pixel_fraction=1e-4, hot_pixel_counts=1000.0,
    dead_pixel_fraction=1e-5, throughput_spread=0.1, vignetting=0.2, glow=0.02,
    brightness_sigma_ln=0.3, pulse_ratio=0.85)


# ---- the camera instance --------------------------------------------------------------------

# one random stream of the camera seed per effect
_STREAM_COLUMN, _STREAM_PIXEL, _STREAM_DEFECT, _STREAM_HOT, _STREAM_LENSLET, _STREAM_GLOW = \
    range(1, 7)


@dataclass(frozen=True, eq=False)
class CameraInstance:
    """One physical camera: the settings and what its camera seed drew.

    Attributes
    ----------
    settings : RecordingSettings
    seed : int
        The camera seed.
    shape : (int, int)
        Sensor shape ``(rows, cols)``.
    column_offset : ndarray, shape (cols,)
        Offset of each column, counts (zeros when off).
    pixel_offset : ndarray, shape (rows, cols), float32, or None
        Offset of each pixel, counts (None when off).
    hot_index, dead_index : ndarray of int64
        Flat indices (``row * cols + col``) of the hot and of the dead pixels, ascending.
    hot_counts : ndarray
        Dark signal of each hot pixel per frame, counts.
    throughput : ndarray, shape (n_lenslets,)
        Throughput factor of each lenslet, row-major lenslet order.
    glow_blobs : ndarray, shape (GLOW_BLOBS, 4)
        The glow's Gaussian blobs: centre row and col (fractions of the sensor's rows and
        cols), sigma (fraction of its larger side) and amplitude.
    """

    settings: RecordingSettings
    seed: int
    shape: tuple[int, int]
    column_offset: np.ndarray
    pixel_offset: np.ndarray | None
    hot_index: np.ndarray
    hot_counts: np.ndarray
    dead_index: np.ndarray
    throughput: np.ndarray
    glow_blobs: np.ndarray

    @property
    def hot_mask(self) -> np.ndarray:
        """Boolean (rows, cols): the hot pixels."""
        return _mask(self.shape, self.hot_index)

    @property
    def dead_mask(self) -> np.ndarray:
        """Boolean (rows, cols): the dead pixels."""
        return _mask(self.shape, self.dead_index)

    @property
    def offset(self) -> np.ndarray:
        """The fixed offset of every pixel (black level and fixed pattern), counts, float64."""
        off = np.full(self.shape, float(self.settings.black_level_counts))
        off += self.column_offset[None, :]
        if self.pixel_offset is not None:
            off += self.pixel_offset
        return off


def _mask(shape, index) -> np.ndarray:
    m = np.zeros(shape, dtype=bool)
    m.flat[index] = True
    return m


def _stream(seed: int, k: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), k])


def camera_instance(camera: CameraModel, recording: RecordingSettings | None = None, *,
                    seed: int = 0) -> CameraInstance:
    """Draw the fixed pattern, the defects and the lenslet throughputs of one camera.

    Parameters
    ----------
    camera : CameraModel
        Gives the sensor shape and the lenslet count.
    recording : RecordingSettings, optional
        The effects (default: none).
    seed : int
        The camera seed, >= 0. The same seed and settings give the same camera; each effect
        draws from its own stream, so that turning one on or off changes no other.
    """
    s = RecordingSettings() if recording is None else recording
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"camera seed = {seed!r}: expected an integer >= 0")
    rows, cols = camera.sensor.shape
    n = rows * cols
    col_off = np.zeros(cols)
    if s.column_offset_counts > 0:
        col_off = s.column_offset_counts * _stream(seed, _STREAM_COLUMN).standard_normal(cols)
    pix_off = None
    if s.pixel_offset_counts > 0:
        pix_off = _stream(seed, _STREAM_PIXEL).standard_normal((rows, cols), dtype=np.float32)
        pix_off *= np.float32(s.pixel_offset_counts)
    hot = dead = np.zeros(0, dtype=np.int64)
    if s.hot_pixel_fraction > 0 or s.dead_pixel_fraction > 0:
        # one uniform number per pixel: hot below the hot fraction, dead above one minus the
        # dead fraction, so that a larger fraction adds defects to the same camera's
        u = _stream(seed, _STREAM_DEFECT).random(n, dtype=np.float32)
        hot = np.flatnonzero(u < s.hot_pixel_fraction)
        dead = np.flatnonzero(u >= np.float32(1.0 - s.dead_pixel_fraction)) \
            if s.dead_pixel_fraction > 0 else dead
    lo, hi = HOT_SPREAD
    hot_counts = s.hot_pixel_counts * _stream(seed, _STREAM_HOT).uniform(lo, hi, len(hot))
    count = camera.microlens_array.count
    throughput = np.ones(count)
    if s.throughput_spread > 0:
        throughput = 1.0 + s.throughput_spread * _stream(seed, _STREAM_LENSLET).uniform(
            -1.0, 1.0, count)
    g = _stream(seed, _STREAM_GLOW)
    blobs = np.column_stack([g.uniform(-0.25, 1.25, GLOW_BLOBS),
                             g.uniform(-0.25, 1.25, GLOW_BLOBS),
                             g.uniform(0.3, 0.8, GLOW_BLOBS),
                             g.uniform(0.3, 1.0, GLOW_BLOBS)])
    return CameraInstance(s, int(seed), (rows, cols), col_off, pix_off, hot, hot_counts, dead,
                          throughput, blobs)


# ---- optics and light -----------------------------------------------------------------------


def vignetting_coefficient(vignetting: float) -> float:
    """``a`` of the fall-off ``(1 + a ρ²)^-2`` that loses ``vignetting`` of the light at ρ = 1."""
    return (1.0 - vignetting) ** -0.5 - 1.0


def optical_gain(camera: CameraModel, instance: CameraInstance, *,
                 sensor_shift_px=(0.0, 0.0), engine: str = "numba") -> np.ndarray | None:
    """The share of the light each pixel gets from its lenslet: throughput × vignetting.

    Returns a (rows, cols) float64 map, or None when the instance has neither effect.

    Parameters
    ----------
    camera : CameraModel
    instance : CameraInstance
        Its ``throughput`` and ``settings.vignetting``.
    sensor_shift_px : (2,) float
        The render's sensor shift: the map moves with the image content.
    engine : {"numba", "numpy"}
        The kernel or its NumPy twin (small sensors only).

    Notes
    -----
    A pixel belongs to the micro-image it lies in, the image of the aperture through one
    lenslet, centred where the chief ray from the exit pupil through that lenslet's centre
    meets the sensor (:func:`~plenopiv.camera.optics.focal_spot_exact`); the micro-images
    form the lenslet lattice magnified by ``p/d`` (Eq. 3.11,
    :func:`~plenopiv.camera.optics.focal_spot_scale`). The fall-off is radial about that
    centre with ρ = 1 at half the micro-images' pitch, or (``vignetting_centre =
    "lenslet"``) about the lenslet's axis, the point of the sensor under its centre, with
    ρ = 1 at half the lenslets' pitch.
    """
    from plenopiv.synthetic import _sensor_kernels as SK
    from plenopiv.synthetic.tracer import check_render_options, geometry_vector

    s = instance.settings
    if not s.has_optics:
        return None
    if tuple(camera.sensor.shape) != tuple(instance.shape) \
            or len(instance.throughput) != camera.microlens_array.count:
        raise ConfigError(f"camera instance of a {instance.shape[0]} × {instance.shape[1]}-"
                          f"pixel sensor with {len(instance.throughput)} lenslets used with "
                          f"the camera {camera.name!r} ({camera.sensor.rows} × "
                          f"{camera.sensor.cols}, {camera.microlens_array.count} lenslets)")
    if engine not in ("numba", "numpy"):
        raise ConfigError(f"engine = {engine!r}: expected 'numba' or 'numpy'")
    d_row, d_col = check_render_options("bilinear", 0.0, sensor_shift_px)
    g = geometry_vector(camera)
    mla = camera.microlens_array
    scale = float(focal_spot_scale(camera.image_distance, mla.sensor_distance,
                                   back_side=mla.back_side, thickness=camera.plate_thickness,
                                   refractive_index=camera.plate_index,
                                   pupil_offset=camera.main_lens.exit_pupil_offset))
    a = vignetting_coefficient(s.vignetting)
    centres = mla.centres()
    if s.vignetting_centre == "lenslet":
        rim = 0.5 * mla.pitch
    else:
        rim = 0.5 * mla.pitch * scale
        centres = focal_spot_exact(centres, camera.image_distance, mla.sensor_distance,
                                   back_side=mla.back_side, thickness=camera.plate_thickness,
                                   refractive_index=camera.plate_index,
                                   pupil_offset=camera.main_lens.exit_pupil_offset)
    centres = np.ascontiguousarray(centres, dtype=np.float64)
    tp = np.ascontiguousarray(instance.throughput, dtype=np.float64)
    if engine == "numpy":
        return SK.optical_gain_numpy(g, scale, d_row, d_col, tp, centres, a, rim)
    out = np.empty(camera.sensor.shape)
    run_slices(SK.optical_gain, out.shape[0], g, scale, d_row, d_col, tp, centres, a, rim,
               out)
    return out


def particle_peak_irradiance(camera: CameraModel, f_number: float | None = None) -> float:
    """Irradiance of an in-focus particle of unit brightness, per pixel (the glow's unit).

    The particle's light fills one micro-image, a disc of radius ``f̄ D / (2 S_i)`` with
    ``D = f_m / N`` the aperture; spread evenly over it, each pixel gets
    ``p_p² / (π r²)`` of it.
    """
    n = camera.main_lens.f_number if f_number is None else float(f_number)
    r = camera.microlens_array.sensor_distance * camera.main_lens.focal_length / n / 2.0 \
        / camera.image_distance
    return camera.sensor.pixel_pitch ** 2 / (math.pi * r * r)


def glow_field(instance: CameraInstance) -> np.ndarray:
    """The glow's smooth field on the sensor, peak 1, (rows, cols) float64.

    A sum of :data:`GLOW_BLOBS` broad Gaussians (sigma 0.3 to 0.8 of the sensor's larger
    side) centred anywhere within a quarter of the sensor beyond its edges.
    """
    rows, cols = instance.shape
    big = max(rows, cols)
    r = np.arange(rows, dtype=float)
    c = np.arange(cols, dtype=float)
    out = np.zeros((rows, cols))
    for r0, c0, sig, amp in instance.glow_blobs:
        gr = np.exp(-0.5 * ((r - r0 * rows) / (sig * big)) ** 2)
        gc = np.exp(-0.5 * ((c - c0 * cols) / (sig * big)) ** 2)
        out += amp * np.outer(gr, gc)
    return out / out.max()


def sheet_illumination(depth, recording: RecordingSettings) -> np.ndarray:
    """Relative light intensity at depth ``depth`` (metres, Z): the sheet's profile.

    "none": 1; "gaussian": ``exp(-4 ln2 (Z - Z_c)² / w²)`` (w the full width at half
    maximum); "tophat": 1 within ``|Z - Z_c| <= w / 2``, else 0.
    """
    z = np.asarray(depth, dtype=float)
    s = recording
    if s.sheet_profile == "none":
        return np.ones_like(z)
    zc, w = s.sheet_centre_mm * 1e-3, s.sheet_thickness_mm * 1e-3
    if s.sheet_profile == "gaussian":
        return np.exp(-4.0 * math.log(2.0) * ((z - zc) / w) ** 2)
    return (np.abs(z - zc) <= 0.5 * w).astype(float)


def particle_brightness(n: int, recording: RecordingSettings,
                        rng: np.random.Generator) -> np.ndarray | None:
    """Brightness of ``n`` particles: log-normal, median 1; None (all 1) when the spread is 0.

    Draws nothing from ``rng`` when the spread is 0.
    """
    if recording.brightness_sigma_ln <= 0:
        return None
    return rng.lognormal(0.0, recording.brightness_sigma_ln, int(n))


# ---- the sensor -----------------------------------------------------------------------------


def adc_full_scale(recording: RecordingSettings, bit_depth: int | None) -> float:
    """The largest count the ADC gives: 2^adc_bits - 1 (adc_bits: the file's by default)."""
    if bit_depth is None:
        raise ConfigError("a sensor model (black level, fixed pattern, read noise, gain, ADC "
                          "bits, hot or dead pixels) records integer counts: give a bit "
                          "depth of 8 or 16, not float output")
    bits = bit_depth if recording.adc_bits is None else recording.adc_bits
    if bits > bit_depth:
        raise ConfigError(f"adc_bits = {bits}: more than the file's {bit_depth} bits; write "
                          "16-bit files or lower adc_bits")
    return float(2 ** bits - 1)


def record(counts, instance: CameraInstance, *, noise: str, full_well: float, bit_depth: int,
           rng: np.random.Generator | None) -> np.ndarray:
    """Record the exposed signal ``counts`` (counts above black, float) as the sensor reads out.

    Parameters
    ----------
    counts : ndarray, (rows, cols)
        The light's signal in counts (irradiance times the exposure); negative values are 0.
    instance : CameraInstance
    noise : {"none", "poisson"}
        "poisson": shot noise of the photo-electrons and of the hot pixels' dark electrons.
    full_well : float
        Electrons a pixel holds; more are lost.
    bit_depth : {8, 16}
        The file's integer type.
    rng : numpy.random.Generator
        The frame's noise; needed for shot noise and read noise.

    Notes
    -----
    ``e = counts / g`` photo-electrons (g counts per electron, ``gain_counts_per_electron``
    or ADC full scale / full well), zero on dead pixels; plus ``d / g`` dark electrons on hot
    pixels (d their dark signal in counts); Poisson when ``noise`` is "poisson"; at most the
    full well. Then ``g e`` plus the black level, the column and pixel offsets and the read
    noise, rounded to integers and clipped to ``[0, 2^adc_bits - 1]``.
    """
    s = instance.settings
    full = adc_full_scale(s, bit_depth)
    gain = s.gain_counts_per_electron or full / full_well
    sig = np.asarray(counts, dtype=np.float64)
    if sig.shape != tuple(instance.shape):
        raise ConfigError(f"image of shape {sig.shape} recorded by a camera instance of shape "
                          f"{tuple(instance.shape)}")
    if (noise == "poisson" or s.read_noise_counts > 0) and rng is None:
        raise ConfigError("shot or read noise needs a random generator (rng=...)")
    e = np.clip(sig, 0.0, None) / gain
    if len(instance.hot_index):
        e.flat[instance.hot_index] += instance.hot_counts / gain
    if len(instance.dead_index):
        e.flat[instance.dead_index] = 0.0
    if noise == "poisson":
        e = rng.poisson(e).astype(np.float64)
    np.minimum(e, full_well, out=e)
    out = e * gain
    out += instance.offset
    if s.read_noise_counts > 0:
        out += rng.normal(0.0, s.read_noise_counts, out.shape)
    np.rint(out, out=out)
    np.clip(out, 0.0, full, out=out)
    return out.astype(np.uint8 if bit_depth == 8 else np.uint16)


def describe(instance: CameraInstance) -> dict:
    """The instance for a file's metadata: every setting and the camera seed."""
    return {"camera_seed": instance.seed, "settings": dataclasses.asdict(instance.settings)}
