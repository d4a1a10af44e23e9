"""Synthetic plenoptic images: focal-point, alignment, ruler and particle images.

Every function returns irradiance (float64, arbitrary units) with exactly the camera's sensor
shape, ``image[row, col]`` as the sensor reads out. :func:`finish_image` turns irradiance into
a recorded image (blur, photon noise, quantisation).

Given a :class:`~plenopiv.synthetic.sensor.CameraInstance` (``instance=``), a render also
carries that camera's lenslet throughputs and micro-image vignetting (applied to the traced
irradiance), a particle image its light (depth profile, pulse energy, glow), and
:func:`finish_image` records through its sensor (:mod:`plenopiv.synthetic.sensor`). Without
one, or with one whose settings are all off, the images are the ideal ones, bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from plenopiv.camera.model import CameraModel
from plenopiv.errors import ConfigError
from plenopiv.synthetic.sensor import (
    CameraInstance,
    adc_full_scale,
    glow_field,
    optical_gain,
    particle_peak_irradiance,
    record,
    sheet_illumination,
)
from plenopiv.synthetic.tracer import (
    Progress,
    render_lenslet_bundles,
    render_sources,
    symmetric_disc_points,
)


def focal_point_image(camera: CameraModel, *, f_number: float | None = None,
                      pupil_across: int = 15, cell_across: int = 2,
                      progress: Progress = None, splat: str = "bilinear", psf_px: float = 0.0,
                      sensor_shift_px=(0.0, 0.0),
                      instance: CameraInstance | None = None) -> np.ndarray:
    """Focal-point calibration image: a white sheet seen through the stopped-down lens.

    Parameters
    ----------
    camera : CameraModel
    f_number : float, optional
        Stop used for the calibration image (default: the camera's f-number). The stop's
        centre sits at the exit pupil, z = ``exit_pupil_offset``.
    pupil_across : int
        Pupil samples across the stop diameter (a symmetric grid clipped to the disc).
    cell_across : int
        Samples across each lenslet's cell.
    progress : callable, optional
        Called with the number of lenslets done after each batch.
    splat : {"bilinear", "pixel"}
        How a ray lands on the pixels: ``"bilinear"`` (default) shares it among the four
        nearest pixel centres by area (a one-pixel box around the ray), ``"pixel"`` puts it
        wholly into the pixel it hits (a sensor integrating over its pixels).
    psf_px : float
        Standard deviation of a Gaussian point-spread function, pixels (diffraction, optics),
        applied before the pixels integrate (default 0: none).
    sensor_shift_px : (2,) float
        The sensor sits shifted so that the image content moves by ``(d_row, d_col)``
        pixels (default none).
    instance : CameraInstance, optional
        A real camera: its lenslet throughputs and micro-image vignetting
        (:func:`~plenopiv.synthetic.sensor.optical_gain`) scale the irradiance.

    Notes
    -----
    Each lenslet receives the light of the whole stop; the centroid of its spot is where the
    chief ray from the stop centre through the lenslet centre meets the sensor (thesis
    §3.1.1, Eqs. 3.11 and 4.8). Each spot is weighted by cos⁴ of its chief ray (natural
    vignetting), uniformly within the spot, so the vignetting does not bias the centroid.
    """
    if f_number is not None and not (np.isfinite(f_number) and f_number > 0):
        raise ConfigError(f"f_number = {f_number!r}: expected a finite number > 0 (or None "
                          "for the camera's)")
    radius = camera.main_lens.focal_length / (f_number or camera.main_lens.f_number) / 2
    pupil = symmetric_disc_points(radius, pupil_across)
    irr = render_lenslet_bundles(camera, pupil_points=pupil, cell_across=cell_across,
                                 collimated=False, f_number=f_number, progress=progress,
                                 splat=splat, psf_px=psf_px, sensor_shift_px=sensor_shift_px)
    return _through_optics(camera, irr, instance, sensor_shift_px)


def _through_optics(camera: CameraModel, irr: np.ndarray, instance: CameraInstance | None,
                    sensor_shift_px) -> np.ndarray:
    """``irr`` times the instance's optical gain (throughput, vignetting); as is without."""
    if instance is None:
        return irr
    gain = optical_gain(camera, instance, sensor_shift_px=sensor_shift_px)
    if gain is None:
        return irr
    irr *= gain
    return irr


#: Pupil samples per pixel across a micro-image in a white image (the splat of a regular
#: grid of rays spaced 1/3 pixel ripples by less than 1 %).
WHITE_SAMPLES_PER_PIXEL = 3.0


def white_image(camera: CameraModel, *, f_number: float | None = None,
                instance: CameraInstance | None = None, progress: Progress = None,
                splat: str = "bilinear", psf_px: float = 0.0,
                sensor_shift_px=(0.0, 0.0)) -> np.ndarray:
    """A white image for a flat field: a uniform white sheet seen at the recording's aperture.

    The focal-point image (:func:`focal_point_image`) at ``f_number`` (default: the
    camera's), its stop sampled finely enough (:data:`WHITE_SAMPLES_PER_PIXEL`) that every
    micro-image is evenly lit: the micro-images of the recording with the natural vignetting
    of the main lens and, given ``instance``, its lenslets' throughputs and vignetting.
    """
    n = camera.main_lens.f_number if f_number is None else f_number
    if not (np.isfinite(n) and n > 0):
        raise ConfigError(f"f_number = {f_number!r}: expected a finite number > 0 (or None "
                          "for the camera's)")
    diameter_px = (camera.microlens_array.sensor_distance * camera.main_lens.focal_length / n
                   / camera.image_distance / camera.sensor.pixel_pitch)
    across = max(15, int(np.ceil(WHITE_SAMPLES_PER_PIXEL * diameter_px)))
    return focal_point_image(camera, f_number=n, pupil_across=across, progress=progress,
                             splat=splat, psf_px=psf_px, sensor_shift_px=sensor_shift_px,
                             instance=instance)


def alignment_image(camera: CameraModel, *, cell_across: int = 8,
                    progress: Progress = None, splat: str = "bilinear", psf_px: float = 0.0,
                    sensor_shift_px=(0.0, 0.0),
                    instance: CameraInstance | None = None) -> np.ndarray:
    """Alignment image: collimated light along the axis, main lens removed (thesis §2.5).

    Each lenslet focuses its share a distance f_l behind it, under its own centre (an ideal
    lenslet makes that a point: give ``psf_px`` for the diffraction spot of a real one).
    ``splat``, ``psf_px``, ``sensor_shift_px``, ``instance``: as in :func:`focal_point_image`.
    """
    irr = render_lenslet_bundles(camera, pupil_points=None, cell_across=cell_across,
                                 collimated=True, progress=progress, splat=splat,
                                 psf_px=psf_px, sensor_shift_px=sensor_shift_px)
    return _through_optics(camera, irr, instance, sensor_shift_px)


def field_of_view(camera: CameraModel, depth: float = 0.0) -> tuple[float, float]:
    """Object-space half-widths (X, Y) in metres seen by the lenslet array at depth ``depth``."""
    width, height = camera.microlens_array.extent
    so = camera.object_distance
    ext = camera.external_interface
    eff_depth = depth if ext is None else depth * ext.depth_ratio
    scale = (so + eff_depth) / camera.image_distance
    return 0.5 * width * scale, 0.5 * height * scale


@dataclass(frozen=True)
class Ruler:
    """A ruler on a plane parallel to the sensor: dark ticks across x on a white ground.

    Attributes
    ----------
    spacing : float
        Tick spacing, metres (ticks at X = k · spacing).
    tick_width : float
        Width of a tick, metres.
    depth : float
        Z of the ruler plane from the nominal focal plane, metres.
    tick_reflectance : float
        Reflectance of the ticks relative to the ground (0 = black).
    """

    spacing: float = 1e-3
    tick_width: float = 0.15e-3
    depth: float = 0.0
    tick_reflectance: float = 0.05

    def __post_init__(self):
        if not self.spacing > 0:
            raise ConfigError(f"ruler spacing = {self.spacing!r} m: expected > 0")
        if not 0 < self.tick_width < self.spacing:
            raise ConfigError(f"ruler tick_width = {self.tick_width!r} m: expected between 0 "
                              f"and the spacing {self.spacing!r} m")
        if not 0 <= self.tick_reflectance < 1:
            raise ConfigError(f"ruler tick_reflectance = {self.tick_reflectance!r}: "
                              "expected in [0, 1)")


def ruler_image(camera: CameraModel, ruler: Ruler = Ruler(), *, rays_per_lenslet: int = 2000,
                emitters_per_lenslet: int = 4, f_number: float | None = None, seed: int = 0,
                progress: Progress = None, splat: str = "bilinear", psf_px: float = 0.0,
                sensor_shift_px=(0.0, 0.0),
                instance: CameraInstance | None = None) -> np.ndarray:
    """Image of a ruler (:class:`Ruler`) filling the field of view at ``ruler.depth``.

    ``splat``, ``psf_px``, ``sensor_shift_px``, ``instance``: as in
    :func:`focal_point_image`.

    The ruler plane is tiled with small square emitting cells (``emitters_per_lenslet`` per
    lenslet footprint along each axis); each ray starts at a random point of its cell, so the
    plane is a continuous source, and the tick pattern is evaluated at that point.
    """
    hx, hy = field_of_view(camera, ruler.depth)
    hx, hy = 1.05 * hx, 1.05 * hy
    mla = camera.microlens_array
    footprint = mla.pitch * (camera.object_distance / camera.image_distance)
    cell = footprint / max(1, emitters_per_lenslet)
    nx, ny = int(np.ceil(2 * hx / cell)), int(np.ceil(2 * hy / cell))
    xs = (np.arange(nx) - (nx - 1) / 2) * cell
    ys = (np.arange(ny) - (ny - 1) / 2) * cell
    X, Y = np.meshgrid(xs, ys, indexing="xy")
    pts = np.stack([X.ravel(), Y.ravel(), np.full(X.size, ruler.depth)], axis=1)
    src = camera.volume_to_camera(pts)
    samples = max(1, int(round(rays_per_lenslet / max(1, emitters_per_lenslet) ** 2)))
    weights = np.full(len(src), 1.0 / max(1, emitters_per_lenslet) ** 2)
    irr = render_sources(camera, src, weights, samples=samples, seed=seed,
                         half_size=(cell / 2, cell / 2),
                         ruler=(ruler.spacing, ruler.tick_width, ruler.tick_reflectance),
                         f_number=f_number, progress=progress, splat=splat, psf_px=psf_px,
                         sensor_shift_px=sensor_shift_px)
    return _through_optics(camera, irr, instance, sensor_shift_px)


def particle_image(camera: CameraModel, positions, intensities=None, *,
                   rays_per_particle: int = 4096, f_number: float | None = None, seed: int = 0,
                   progress: Progress = None, splat: str = "bilinear", psf_px: float = 0.0,
                   sensor_shift_px=(0.0, 0.0), instance: CameraInstance | None = None,
                   pulse_energy: float = 1.0) -> np.ndarray:
    """Image of point particles.

    Parameters
    ----------
    camera : CameraModel
    positions : array_like, shape (N, 3)
        Volume coordinates (X, Y, Z) in metres; Z is the physical depth from the nominal
        focal plane, + away from the camera (in the medium behind an external interface).
    intensities : array_like, shape (N,), optional
        Energy of each particle collected by the full aperture (default 1).
    rays_per_particle : int
        Aperture samples per particle (stratified: a jittered q × q grid mapped to the disc).
    f_number : float, optional
        Overrides the camera's f-number.
    seed : int
        Fixes the aperture jitter; the image does not depend on the thread count.
    splat, psf_px, sensor_shift_px
        Rendering choices, as in :func:`focal_point_image`.
    instance : CameraInstance, optional
        A real camera and its light: each particle's intensity times the depth profile of
        the light at its Z (:func:`~plenopiv.synthetic.sensor.sheet_illumination`), the
        glow added (:func:`~plenopiv.synthetic.sensor.glow_field`), then the lenslets'
        throughputs and vignetting.
    pulse_energy : float
        Energy of the light pulse relative to the first of a pair: scales the particles and
        the glow (default 1).

    Notes
    -----
    Rays are traced exactly: Snell at the external interface (each ray solved to reach its
    lens-plane sample), ideal thin main lens, Snell into the substrate, thin lenslets.
    """
    if isinstance(rays_per_particle, bool) or not isinstance(rays_per_particle,
                                                              (int, np.integer)) \
            or rays_per_particle < 1:
        raise ConfigError(f"rays_per_particle = {rays_per_particle!r}: expected an integer >= 1")
    if f_number is not None and not (np.isfinite(f_number) and f_number > 0):
        raise ConfigError(f"f_number = {f_number!r}: expected a finite number > 0 (or None "
                          "for the camera's)")
    pos = np.asarray(positions, dtype=float)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ConfigError(f"particle positions have shape {pos.shape}: expected (N, 3) (X, Y, Z)")
    if not np.isfinite(pos).all():
        raise ConfigError("particle positions contain NaN or infinity")
    w = np.ones(len(pos)) if intensities is None else np.asarray(intensities, dtype=float)
    if w.shape != (len(pos),) or (w < 0).any() or not np.isfinite(w).all():
        raise ConfigError(f"particle intensities have shape {w.shape}: expected ({len(pos)},) "
                          "finite values >= 0")
    if not (np.isfinite(pulse_energy) and pulse_energy > 0):
        raise ConfigError(f"pulse_energy = {pulse_energy!r}: expected a finite number > 0")
    src = camera.volume_to_camera(pos)
    if (src[:, 2] >= -camera.main_lens.focal_length).any():
        raise ConfigError("a particle lies within one focal length of the main lens "
                          f"(Z <= {(-camera.main_lens.focal_length - camera.focal_plane_z):.4g} m)")
    if instance is not None and instance.settings.sheet_profile != "none":
        w = w * sheet_illumination(pos[:, 2], instance.settings)
    if pulse_energy != 1.0:
        w = w * pulse_energy
    irr = render_sources(camera, src, w, samples=rays_per_particle, seed=seed,
                         f_number=f_number, progress=progress, splat=splat, psf_px=psf_px,
                         sensor_shift_px=sensor_shift_px)
    if instance is not None and instance.settings.glow > 0:
        irr += (instance.settings.glow * pulse_energy
                * particle_peak_irradiance(camera, f_number)) * glow_field(instance)
    return _through_optics(camera, irr, instance, sensor_shift_px)


NOISE_MODELS = ("none", "poisson")


def blurred(image, sigma_px: float) -> np.ndarray:
    """``image`` blurred so that every spot's variance grows by ``sigma_px**2`` per axis, float64.

    Repeated [a, 1 - 2a, a] kernels along each axis, ``n = ceil(1.5 sigma_px**2)`` passes with
    ``a = sigma_px**2 / (2 n)`` (at most 1/3: non-negative, the light kept): each adds
    exactly ``2a`` to the variance, and many tend to the Gaussian. A Gaussian kernel sampled
    on the pixels adds less below about a pixel (0.16 px² instead of 0.25 at 0.5 px), and the
    continuous one in Fourier space rings there. Dark beyond the image's edges.
    """
    from scipy import ndimage

    img = np.asarray(image, dtype=float)
    if sigma_px <= 0:
        return img.copy()
    var = float(sigma_px) ** 2
    n = int(np.ceil(1.5 * var))
    a = var / (2 * n)
    kernel = np.array([a, 1.0 - 2.0 * a, a])
    for _ in range(n):
        for axis in (0, 1):
            img = ndimage.convolve1d(img, kernel, axis=axis, mode="constant")
    return img


def auto_exposure(irradiance, *, bit_depth: int | None = 16, peak_fraction: float = 0.8,
                  blur_px: float = 0.0, sensor: CameraInstance | None = None) -> float:
    """The exposure :func:`finish_image` chooses: counts per irradiance unit.

    The brightest pixel (after the blur) maps to ``peak_fraction`` of the full scale: of the
    file's (1.0 for float output), or with a sensor model of the ADC's above the black
    level. Fix it from the first frame of a pair, so that the second's pulse energy shows.
    """
    img = np.asarray(irradiance, dtype=np.float64)
    if blur_px > 0:
        img = ndimage.gaussian_filter(img, blur_px, mode="constant")
    if sensor is not None and sensor.settings.has_sensor:
        full = adc_full_scale(sensor.settings, bit_depth) - sensor.settings.black_level_counts
    else:
        full = 1.0 if bit_depth is None else float(2 ** bit_depth - 1)
    peak = img.max()
    return peak_fraction * full / peak if peak > 0 else 1.0


def finish_image(irradiance, *, exposure: float | None = None, blur_px: float = 0.0,
                 noise: str = "none", full_well: float = 20000.0, read_noise: float = 0.0,
                 bit_depth: int | None = 16, peak_fraction: float = 0.8,
                 rng: np.random.Generator | None = None,
                 sensor: CameraInstance | None = None) -> np.ndarray:
    """Turn irradiance into a recorded image.

    Parameters
    ----------
    irradiance : ndarray
        Rendered image (arbitrary units).
    exposure : float, optional
        Digital counts per irradiance unit. Default: the brightest pixel (after blur) maps to
        ``peak_fraction`` of full scale (of 1.0 for float output).
    blur_px : float
        Standard deviation of an optional Gaussian blur, pixels (optics, diffraction).
    noise : {"none", "poisson"}
        "poisson": photon noise with ``full_well`` electrons at full scale, plus Gaussian read
        noise ``read_noise`` (counts).
    bit_depth : {8, 16, None}
        Integer quantisation (uint8/uint16, clipped at full scale), or None for float32.
    rng : numpy.random.Generator, optional
        Required for noise; pass a seeded generator for reproducible images.
    sensor : CameraInstance, optional
        A real camera whose settings have a sensor effect: the exposed signal is recorded by
        :func:`~plenopiv.synthetic.sensor.record` (black level, fixed pattern, gain, shot
        noise, hot and dead pixels, read noise ``sensor.settings.read_noise_counts``, ADC
        saturation); the default exposure then maps the peak to ``peak_fraction`` of the
        ADC's range above the black level. ``read_noise`` must then be 0. Without sensor
        effects, as without ``sensor``.
    """
    if noise not in NOISE_MODELS:
        raise ConfigError(f"noise = {noise!r}: expected one of {NOISE_MODELS}")
    if bit_depth not in (8, 16, None):
        raise ConfigError(f"bit_depth = {bit_depth!r}: expected 8, 16 or None (float)")
    for name, value, strict in (("blur_px", blur_px, False), ("full_well", full_well, True),
                                ("read_noise", read_noise, False),
                                ("peak_fraction", peak_fraction, True)):
        if not (np.isfinite(value) and (value > 0 if strict else value >= 0)):
            raise ConfigError(f"{name} = {value!r}: expected a finite number "
                              f"{'> 0' if strict else '>= 0'}")
    if exposure is not None and not (np.isfinite(exposure) and exposure > 0):
        raise ConfigError(f"exposure = {exposure!r}: expected a finite number > 0")
    img = np.asarray(irradiance, dtype=np.float64)
    if sensor is not None and sensor.settings.has_sensor:
        if read_noise > 0:
            raise ConfigError("read_noise: give a sensor model's read noise as its "
                              "read_noise_counts, not here")
        if exposure is None:
            exposure = auto_exposure(img, bit_depth=bit_depth, peak_fraction=peak_fraction,
                                     blur_px=blur_px, sensor=sensor)
        if blur_px > 0:
            img = ndimage.gaussian_filter(img, blur_px, mode="constant")
        return record(img * exposure, sensor, noise=noise, full_well=full_well,
                      bit_depth=bit_depth, rng=rng)
    if blur_px > 0:
        img = ndimage.gaussian_filter(img, blur_px, mode="constant")
    full = 1.0 if bit_depth is None else float(2 ** bit_depth - 1)
    if exposure is None:
        peak = img.max()
        exposure = peak_fraction * full / peak if peak > 0 else 1.0
    counts = img * exposure
    if noise == "poisson":
        if rng is None:
            raise ConfigError("noise = 'poisson' needs a random generator (rng=...)")
        electrons_per_count = full_well / full
        counts = rng.poisson(np.clip(counts, 0, None) * electrons_per_count) / electrons_per_count
        if read_noise > 0:
            counts = counts + rng.normal(0.0, read_noise, counts.shape)
    counts = np.clip(counts, 0.0, full)
    if bit_depth is None:
        return counts.astype(np.float32)
    return np.rint(counts).astype(np.uint8 if bit_depth == 8 else np.uint16)
