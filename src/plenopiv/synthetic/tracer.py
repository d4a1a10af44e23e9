"""Ray-tracing drivers: the camera as a geometry vector, sampling sets, batched kernel loops.

The loops feed the numba kernels in batches, so that long renders can report progress.

Rendered images are irradiance in arbitrary units (float64, sensor shape, ``image[row, col]``);
:func:`plenopiv.synthetic.images.finish_image` adds blur, noise and quantisation.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy import ndimage

from plenopiv._threads import run_slices
from plenopiv.camera.model import CameraModel
from plenopiv.camera.optics import chief_ray_tangent
from plenopiv.errors import ConfigError
from plenopiv.synthetic import _kernels as K

Progress = Callable[[int], None] | None


SPLATS = ("bilinear", "pixel")


def check_render_options(splat: str, psf_px: float, sensor_shift_px) -> tuple[float, float]:
    """Validate the rendering choices; return the sensor shift as ``(d_row, d_col)`` px."""
    if splat not in SPLATS:
        raise ConfigError(f"splat = {splat!r}: expected one of {SPLATS}")
    if not (math.isfinite(psf_px) and psf_px >= 0):
        raise ConfigError(f"psf_px = {psf_px!r}: expected a finite number >= 0 (pixels)")
    shift = np.asarray(sensor_shift_px, dtype=float)
    if shift.shape != (2,) or not np.all(np.isfinite(shift)):
        raise ConfigError(f"sensor_shift_px = {sensor_shift_px!r}: expected two finite numbers "
                          "(d_row, d_col) in pixels")
    return float(shift[0]), float(shift[1])


def geometry_vector(camera: CameraModel, *, f_number: float | None = None,
                    splat: str = "bilinear", sensor_shift_px=(0.0, 0.0),
                    supersample: int = 1) -> np.ndarray:
    """Pack the camera into the float64 vector the kernels read (slots ``_kernels.G_*``).

    Parameters
    ----------
    camera : CameraModel
        Must give ``[main_lens] image_distance_mm``.
    f_number : float, optional
        Overrides the main lens f-number (the stop radius is f_m / (2 N)).
    splat : {"bilinear", "pixel"}
        How a ray's energy goes onto the pixels (see :mod:`._kernels`).
    sensor_shift_px : (2,) float
        The image content moves by ``(d_row, d_col)`` pixels (the sensor shifted the other
        way under the optics).
    supersample : int
        Pixels per sensor pixel along each axis of the grid rendered onto (the finer grid's
        pixel ``s r + (s - 1) / 2`` is centred on sensor pixel ``r``).
    """
    d_row, d_col = check_render_options(splat, 0.0, sensor_shift_px)
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample = {supersample!r}: expected an integer >= 1")
    mla, lens, sen = camera.microlens_array, camera.main_lens, camera.sensor
    n_f = lens.f_number if f_number is None else float(f_number)
    if not n_f > 0:
        raise ConfigError(f"f_number = {f_number!r}: expected > 0")
    g = np.zeros(K.G_SIZE)
    g[K.G_L3] = camera.l3
    g[K.G_T] = camera.plate_thickness
    g[K.G_N] = camera.plate_index
    g[K.G_ZMLA] = camera.mla_z
    g[K.G_FL] = mla.focal_length
    g[K.G_FBAR] = mla.sensor_distance
    g[K.G_THESIS] = 1.0 if mla.back_side == "thesis" else 0.0
    g[K.G_PITCH] = mla.pitch
    g[K.G_ROWSP] = mla.row_spacing
    g[K.G_ROWS] = mla.rows
    g[K.G_COLS] = mla.cols
    g[K.G_HEX] = 1.0 if mla.grid == "hexagonal" else 0.0
    g[K.G_HEXSHIFT] = mla.hex_shift_mean
    g[K.G_OFFS], g[K.G_OFFT] = mla.offset
    g[K.G_COSG] = math.cos(mla.rotation)
    g[K.G_SING] = math.sin(mla.rotation)
    g[K.G_PIX] = sen.pixel_pitch / s
    g[K.G_NROWS] = sen.rows * s
    g[K.G_NCOLS] = sen.cols * s
    g[K.G_SPLAT] = 1.0 if splat == "pixel" else 0.0
    g[K.G_SHIFTR] = d_row * s
    g[K.G_SHIFTC] = d_col * s
    g[K.G_FM] = lens.focal_length
    g[K.G_E] = lens.exit_pupil_offset
    g[K.G_RPUPIL] = lens.focal_length / n_f / 2.0
    ext = camera.external_interface
    if ext is not None:
        g[K.G_ZINT] = -camera.interface_distance
        g[K.G_NEXT] = ext.refractive_index / ext.outside_index
        g[K.G_HASEXT] = 1.0
    else:
        g[K.G_NEXT] = 1.0
    return g


# ---- sampling sets -------------------------------------------------------------------------


def symmetric_disc_points(radius: float, across: int) -> np.ndarray:
    """Centres of an ``across × across`` grid of square cells clipped to a disc, (P, 2).

    The set is symmetric under (x, y) -> (-x, -y) and (x, y) -> (y, x), so the mean of any
    linear function over it is exact: spot centroids are not biased by the sampling.
    """
    if across < 1:
        raise ValueError(f"pupil samples across = {across}: expected >= 1")
    h = 2.0 * radius / across
    u = (np.arange(across) - (across - 1) / 2.0) * h
    x, y = np.meshgrid(u, u, indexing="xy")
    keep = x * x + y * y <= radius * radius * (1 + 1e-12)
    pts = np.stack([x[keep], y[keep]], axis=1)
    return pts if len(pts) else np.zeros((1, 2))


def cell_points(camera: CameraModel, across: int) -> np.ndarray:
    """Symmetric sample points of one lenslet's cell, lattice frame (unrotated), (M, 2), m.

    Square grids: an ``across × across`` grid of the pitch × pitch cell. Hexagonal grids: a
    grid over the hexagon's bounding box, kept where the centre is the nearest lattice point.
    """
    if across < 1:
        raise ValueError(f"cell samples across = {across}: expected >= 1")
    mla = camera.microlens_array
    p = mla.pitch
    if mla.grid == "square":
        u = (np.arange(across) - (across - 1) / 2.0) * (p / across)
        x, y = np.meshgrid(u, u, indexing="xy")
        return np.stack([x.ravel(), y.ravel()], axis=1)
    half_h = p / math.sqrt(3.0)
    ny = max(1, int(round(across * 2 * half_h / p)))
    ux = (np.arange(across) - (across - 1) / 2.0) * (p / across)
    uy = (np.arange(ny) - (ny - 1) / 2.0) * (2 * half_h / ny)
    x, y = np.meshgrid(ux, uy, indexing="xy")
    x, y = x.ravel(), y.ravel()
    rs = mla.row_spacing
    neighbours = np.array([[p, 0], [-p, 0], [p / 2, rs], [-p / 2, rs], [p / 2, -rs],
                           [-p / 2, -rs]])
    d0 = x * x + y * y
    keep = np.ones_like(x, dtype=bool)
    for nx, ny_ in neighbours:
        keep &= d0 <= (x - nx) ** 2 + (y - ny_) ** 2 + 1e-30
    return np.stack([x[keep], y[keep]], axis=1)


# ---- drivers -------------------------------------------------------------------------------


def _accumulators(shape, *, limit_bytes: float | None = None) -> np.ndarray:
    """One float64 image per parallel chunk, so that threads never write the same pixel.

    ``limit_bytes`` caps the chunks' total memory (at least one chunk); None: one per thread.
    """
    n = K.n_threads()
    if limit_bytes is not None:
        n = max(1, min(n, int(limit_bytes // (8 * shape[0] * shape[1]))))
    return np.zeros((n,) + tuple(shape), dtype=np.float64)


# memory for the accumulators of a supersampled render (a fine grid is s² times the sensor)
_SUPERSAMPLE_BYTES = 1.0e9
# finer-grid pixels per sensor pixel for a "pixel" splat behind a PSF
_PSF_SUPERSAMPLE = 4


class _Render:
    """The grid a render accumulates on, and how it becomes the sensor image.

    ``splat="bilinear"``: the sensor grid; a PSF is a Gaussian filter of the result (the
    bilinear splat samples the irradiance blurred by a one-pixel tent, and blurring before
    or after that leaves every moment the same). ``splat="pixel"`` without a PSF: the sensor
    grid, each ray into its pixel. ``splat="pixel"`` with a PSF of sigma ``psf_px``: the
    optics blur comes before the pixels integrate, so the rays are splatted bilinearly on a
    grid ``_PSF_SUPERSAMPLE`` times finer, blurred there (by sigma reduced by the fine
    tent's own variance) and summed in blocks onto the sensor pixels.
    """

    def __init__(self, camera: CameraModel, f_number, splat, psf_px, sensor_shift_px):
        shift = check_render_options(splat, float(psf_px), sensor_shift_px)
        self.psf = float(psf_px)
        self.shape = camera.sensor.shape
        fine = splat == "pixel" and self.psf > 0
        self.s = _PSF_SUPERSAMPLE if fine else 1
        kernel_splat = "bilinear" if fine else splat
        self.g = geometry_vector(camera, f_number=f_number, splat=kernel_splat,
                                 sensor_shift_px=shift, supersample=self.s)
        grid = (self.shape[0] * self.s, self.shape[1] * self.s)
        self.out = _accumulators(grid, limit_bytes=_SUPERSAMPLE_BYTES if fine else None)

    def run(self, kernel, *args) -> None:
        """Run a render kernel on ``args``, this grid and its accumulators, one thread each."""
        n_chunks = self.out.shape[0]
        run_slices(kernel, n_chunks, *args, self.g, self.out, parts=n_chunks)

    def image(self) -> np.ndarray:
        img = _reduce(self.out)
        s = self.s
        if s > 1:
            sigma = math.sqrt(max(self.psf ** 2 - 1.0 / (6.0 * s * s), 0.0)) * s
            img = ndimage.gaussian_filter(img, sigma, mode="constant", truncate=5.0)
            img = img.reshape(self.shape[0], s, self.shape[1], s).sum(axis=(1, 3))
        elif self.psf > 0:
            img = ndimage.gaussian_filter(img, self.psf, mode="constant", truncate=5.0)
        return img


def _reduce(out: np.ndarray) -> np.ndarray:
    """Sum the per-chunk images in place into the first one (no extra full-size copy)."""
    for i in range(1, out.shape[0]):
        out[0] += out[i]
    return out[0]


def _batches(n: int, n_batches: int):
    edges = np.linspace(0, n, min(n_batches, max(n, 1)) + 1).astype(int)
    return [(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]


def chief_ray_weights(camera: CameraModel, centres: np.ndarray) -> np.ndarray:
    """cos⁴ of the chief-ray angle to each lenslet centre: the natural vignetting."""
    rho = np.hypot(centres[:, 0], centres[:, 1])
    air = camera.l3 - camera.main_lens.exit_pupil_offset
    m = chief_ray_tangent(rho, air, camera.plate_thickness, camera.plate_index)
    return 1.0 / (1.0 + m * m) ** 2


def render_lenslet_bundles(camera: CameraModel, *, pupil_points: np.ndarray | None,
                           cell_across: int, collimated: bool, f_number: float | None = None,
                           progress: Progress = None, n_batches: int = 32,
                           splat: str = "bilinear", psf_px: float = 0.0,
                           sensor_shift_px=(0.0, 0.0)) -> np.ndarray:
    """Render a uniform source seen through a stop (or collimated light), lenslet by lenslet.

    ``splat``, ``psf_px`` and ``sensor_shift_px`` are the rendering choices of
    :func:`plenopiv.synthetic.images.focal_point_image`. Returns the irradiance image
    (float64, sensor shape).
    """
    r = _Render(camera, f_number, splat, psf_px, sensor_shift_px)
    centres = camera.microlens_array.centres()
    weights = np.ones(len(centres)) if collimated else chief_ray_weights(camera, centres)
    cells = cell_points(camera, cell_across)
    pupil = np.zeros((1, 2)) if pupil_points is None else np.ascontiguousarray(pupil_points)
    for a, b in _batches(len(centres), n_batches):
        r.run(K.render_lenslet_bundles, np.ascontiguousarray(centres[a:b]), weights[a:b],
              cells, pupil, collimated)
        if progress is not None:
            progress(b - a)
    return r.image()


def render_sources(camera: CameraModel, sources: np.ndarray, weights: np.ndarray, *,
                   samples: int, seed: int, half_size=(0.0, 0.0), ruler=(0.0, 0.0, 1.0),
                   f_number: float | None = None, progress: Progress = None,
                   n_batches: int = 32, splat: str = "bilinear", psf_px: float = 0.0,
                   sensor_shift_px=(0.0, 0.0)) -> np.ndarray:
    """Render point (or small area) sources given in camera coordinates (N, 3), z < 0."""
    r = _Render(camera, f_number, splat, psf_px, sensor_shift_px)
    src = np.ascontiguousarray(sources, dtype=np.float64)
    w = np.ascontiguousarray(weights, dtype=np.float64)
    hs = np.asarray(half_size, dtype=np.float64)
    rl = np.asarray(ruler, dtype=np.float64)
    for a, b in _batches(len(src), n_batches):
        r.run(K.render_sources, src[a:b], w[a:b], hs, int(samples), int(seed), a, rl)
        if progress is not None:
            progress(b - a)
    return r.image()
