"""Sensor defects of a calibration image: black level, fixed pattern and hot pixels.

A recorded calibration image is the light plus a black level (an offset that may differ
column by column and row by row: the fixed pattern), read noise and hot pixels. With a dark
frame the calibration subtracts it and ignores the hot pixels it shows
(:func:`hot_pixels_from_dark`); without one it estimates the black level from the dark gaps
between the spots (:func:`fixed_pattern`) and finds the hot pixels by their shape
(:func:`isolated_pixels`). :func:`patch_pixels` replaces the pixels found by the median of
their good neighbours. Pixels are ``(row, col)`` (:mod:`plenopiv.conventions`).

See docs/methods.md#sensor-defects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from plenopiv.errors import ImageError

# A dark-frame pixel this many robust standard deviations above its 3 x 3 median is hot
HOT_DARK_SIGMA = 8.0
# A calibration-image pixel is an isolated hot pixel when it stands this many noise standard
# deviations above its background and its brightest 4-neighbour holds less than this fraction
# of its height (a spot of rms radius >= 1 px: the 4-neighbours of its peak hold >= 0.37)
HOT_IMAGE_SIGMA = 8.0
HOT_NEIGHBOUR_FRACTION = 0.25
# Hot pixels are told by their shape where the spots' measured rms radius (pixel width
# included) is at least this: a Gaussian spot of sigma 0.53 px per axis, centred on a pixel,
# measures 0.85 px and its 4-neighbours hold 0.25 of its peak; at 0.9 px they hold 0.29, and
# a spot off a pixel's centre has a brighter neighbour still
HOT_SHAPE_MIN_RMS_PX = 0.9
# The fixed pattern is estimated where at least this fraction of the image is dark gap, and
# the gaps' noise is less than this fraction of the brightest light above them
MIN_DARK_FRACTION = 0.5
MAX_GAP_NOISE = 0.05


def _mad_sigma(values) -> float:
    """Robust standard deviation: 1.4826 times the median absolute deviation."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        return 0.0
    return 1.4826 * float(np.median(np.abs(v - np.median(v))))


def hot_pixels_from_dark(dark, *, sigma: float = HOT_DARK_SIGMA) -> np.ndarray:
    """The hot pixels of a dark frame: a boolean mask of its shape.

    Parameters
    ----------
    dark : array_like, shape (R, C)
        A dark frame (no light, the exposure of the images), counts.
    sigma : float
        A pixel is hot when it exceeds the median of its 3 x 3 neighbourhood by this many
        robust standard deviations of that difference over the frame (default 8).

    Returns
    -------
    ndarray of bool, shape (R, C)
    """
    d = np.asarray(dark, dtype=np.float32)
    excess = d - ndi.median_filter(d, size=3, mode="nearest")
    noise = _mad_sigma(excess[:: max(1, excess.shape[0] // 512), :: max(1, excess.shape[1] // 512)])
    floor = max(noise, 1e-6 * max(float(np.abs(d).max()), 1.0))
    return excess > sigma * floor


def patch_pixels(image, mask) -> np.ndarray:
    """``image`` with the pixels of ``mask`` replaced by the median of their good neighbours.

    The neighbours are the 3 x 3 pixels around each one not in ``mask`` (5 x 5 when all eight
    are masked). Returns a float32 copy; ``image`` is not changed.
    """
    out = np.array(image, dtype=np.float32, copy=True)
    m = np.asarray(mask, dtype=bool)
    if m.shape != out.shape:
        raise ImageError(f"the pixel mask is {m.shape[0]} × {m.shape[1]}; expected the image's "
                         f"{out.shape[0]} × {out.shape[1]}")
    rows, cols = np.nonzero(m)
    if rows.size == 0:
        return out
    for half in (1, 2):
        dr, dc = np.mgrid[-half:half + 1, -half:half + 1]
        dr, dc = dr.ravel(), dc.ravel()
        rr = np.clip(rows[:, None] + dr[None, :], 0, out.shape[0] - 1)
        cc = np.clip(cols[:, None] + dc[None, :], 0, out.shape[1] - 1)
        vals = np.where(m[rr, cc], np.nan, out[rr, cc])
        good = np.isfinite(vals).any(axis=1)
        if good.any():
            out[rows[good], cols[good]] = np.nanmedian(vals[good], axis=1)
        rows, cols = rows[~good], cols[~good]
        if rows.size == 0:
            break
    return out


def fixed_pattern(image, pitch_px: float) -> np.ndarray:
    """The black level's fixed pattern per column and per row, estimated from the dark gaps.

    Parameters
    ----------
    image : array_like, shape (R, C)
        A calibration image whose spots leave most of it dark (focal-point, alignment image).
    pitch_px : float
        Lenslet pitch, px (sets the regions of the smooth black level).

    Returns
    -------
    ndarray of float32, shape (R, C)
        ``col[c] + row[r]``, each of zero median, to subtract from the image; zero when less
        than :data:`MIN_DARK_FRACTION` of the image is dark gap, or when the darkest pixels
        spread over more than :data:`MAX_GAP_NOISE` of the light (a white image, whose
        micro-images fill their cells, shows no gaps to measure it on).

    Notes
    -----
    The smooth part of the black level is left to the local background of the spot
    detection. The dark gaps are the pixels within 4 robust standard deviations of their
    region's gap level (regions of 4 x 4 pitches, :func:`_dark_gaps`) and farther than 2 px
    from any pixel above it (a spot's faint tail, counted in the columns through the spot,
    would print the spot's profile into the pattern and bias its centre); a column's level is
    the mean of its gap pixels less the smooth level of their regions, likewise a row's after
    the columns are removed, twice. The mean over n gap pixels carries 1/sqrt(n) of the noise
    into the pattern (a few per cent of it); every spot of a lattice column shares it, so it
    is kept small; a pattern whose mean square is within 4 times that noise's is not
    subtracted.
    """
    a = np.asarray(image, dtype=np.float32)
    smooth, sigma = _dark_gaps(a, pitch_px)
    bright = float(np.percentile(a[::4, ::4], 99.5)) - float(np.median(smooth))
    if not float(np.median(sigma)) < MAX_GAP_NOISE * bright:
        return np.zeros_like(a)     # no dark gaps: the "gap" level spreads over the light
    resid = a - smooth
    col = np.zeros(a.shape[1], np.float32)
    row = np.zeros(a.shape[0], np.float32)
    for _ in range(2):
        # the second pass takes the gaps against the noise left once the pattern is out;
        # the two pixels around anything brighter are no gap: a spot's faint tail, counted
        # in the columns through it, would print the spots' own profile into the pattern
        left = resid - col[None, :] - row[:, None]
        dark = np.abs(left) <= 4.0 * sigma
        if dark.mean() < MIN_DARK_FRACTION:
            return np.zeros_like(a)
        dark &= ~ndi.maximum_filter(left > 4.0 * sigma, size=2 * _TAIL_PX + 1)
        col = col + _masked_mean(left, dark, axis=0)
        left = resid - col[None, :] - row[:, None]
        row = row + _masked_mean(left, dark, axis=1)
        sigma = np.float32(max(_mad_sigma((resid - col[None, :] - row[:, None])[dark]), 1e-6))
    # a pattern that does not stand out of its own noise is left out (it would add noise)
    col = _significant(col, float(sigma) / np.sqrt(np.maximum(dark.sum(axis=0), 1)))
    row = _significant(row, float(sigma) / np.sqrt(np.maximum(dark.sum(axis=1), 1)))
    return (col[None, :] + row[:, None]).astype(np.float32)


# the fixed pattern leaves out the pixels within _TAIL_PX of one that is lit
_TAIL_PX = 2


def _masked_mean(a, mask, axis):
    """Mean of ``a`` along ``axis`` over the pixels of ``mask``; 0 where fewer than 8."""
    n = mask.sum(axis=axis)
    total = np.where(mask, a, 0.0).sum(axis=axis, dtype=np.float64)
    return np.where(n >= 8, total / np.maximum(n, 1), 0.0).astype(np.float32)


def _significant(pattern, noise):
    """``pattern`` less its median, or zeros when its spread is within twice its noise's."""
    p = pattern - np.median(pattern)
    if np.mean(p * p) <= 4.0 * np.mean(noise * noise):
        return np.zeros_like(p)
    return p


def _dark_gaps(a, pitch_px):
    """The smooth black level and the noise's standard deviation in the gaps, per pixel.

    Per region of 4 x 4 pitches: the median of its pixels below its median, then, four
    times, the median of those within 3 robust standard deviations of the last level (light
    only adds, so the clipped median converges on the gaps' own); the standard deviation
    from the clipped pixels' quartiles; both interpolated bilinearly between the regions'
    centres.
    """
    tile = max(int(math.ceil(4.0 * pitch_px)), 8)
    n_r = max(a.shape[0] // tile, 1)
    n_c = max(a.shape[1] // tile, 1)
    h, w = a.shape[0] // n_r, a.shape[1] // n_c
    blocks = a[:n_r * h, :n_c * w].reshape(n_r, h, n_c, w).transpose(0, 2, 1, 3)
    x = np.sort(blocks.reshape(n_r * n_c, h * w), axis=1)
    m_all = x.shape[1]
    tiles = np.arange(x.shape[0])
    lo = np.zeros(x.shape[0], np.int64)
    hi = np.full(x.shape[0], m_all // 2 + 1, np.int64)
    for _ in range(4):
        n = np.maximum(hi - lo, 1)
        level = x[tiles, np.minimum(lo + n // 2, m_all - 1)]
        q1 = x[tiles, np.minimum(lo + n // 4, m_all - 1)]
        q3 = x[tiles, np.minimum(lo + (3 * n) // 4, m_all - 1)]
        spread = np.maximum((q3 - q1) / 1.349, 1e-6 * np.maximum(np.abs(level), 1.0))
        lo = (x < (level - 3 * spread)[:, None]).sum(axis=1)
        hi = np.maximum((x <= (level + 3 * spread)[:, None]).sum(axis=1), lo + 1)
    shape = (n_r, n_c)
    return (_upsample(level.reshape(shape), a.shape),
            _upsample(spread.reshape(shape), a.shape))


def _upsample(grid, shape):
    """Bilinear interpolation of region values (at the regions' centres) onto every pixel."""
    out = np.asarray(grid, np.float32)
    for axis in (0, 1):
        n_in, n_out = out.shape[axis], shape[axis]
        x = (np.arange(n_out) + 0.5) * n_in / n_out - 0.5
        i0 = np.clip(np.floor(x).astype(np.int64), 0, n_in - 1)
        i1 = np.minimum(i0 + 1, n_in - 1)
        t = np.clip(x - np.floor(x), 0.0, 1.0).astype(np.float32)
        t = np.where(x < 0, 0.0, t).astype(np.float32)
        t = t[:, None] if axis == 0 else t[None, :]
        out = np.take(out, i0, axis=axis) * (1 - t) + np.take(out, i1, axis=axis) * t
    return out


def isolated_pixels(work, noise: float, *, sigma: float = HOT_IMAGE_SIGMA,
                    neighbour_fraction: float = HOT_NEIGHBOUR_FRACTION) -> np.ndarray:
    """Hot pixels of a background-subtracted image, found by their shape: a boolean mask.

    A pixel is hot when it stands ``sigma`` noise standard deviations above the background
    and its brightest 4-neighbour holds less than ``neighbour_fraction`` of its height: light
    confined to one pixel. Use it only on images whose spots are broader than that (a
    measured rms radius of at least :data:`HOT_SHAPE_MIN_RMS_PX`: the 4-neighbours of a
    spot's peak then hold at least 0.29 of it); an alignment image's one-pixel spots would
    be taken for hot pixels.

    Parameters
    ----------
    work : ndarray, shape (R, C)
        Background-subtracted image (gaps near 0).
    noise : float
        Standard deviation of the noise in the gaps, image units.
    """
    w = np.asarray(work, dtype=np.float32)
    pad = np.pad(w, 1, mode="edge")
    n4 = np.maximum.reduce([pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]])
    return (w > sigma * max(float(noise), 1e-12)) & (n4 < neighbour_fraction * w)


def hot_pixel_mask(positions_px, shape) -> np.ndarray:
    """The pixels at ``positions_px`` (``(K, 2)`` ``(row, col)`` px, rounded): a boolean mask.

    Without a dark frame the hot pixels of the alignment image, whose one-pixel spots look
    like them, are those the focal-point image showed by their shape (its spots are broader
    than a pixel: :attr:`~plenopiv.calibration.spot_types.SpotSet.rejected_px`): a hot
    pixel's dark current is in every image the sensor records.
    """
    mask = np.zeros(shape, dtype=bool)
    rc = np.rint(np.asarray(positions_px, dtype=np.float64).reshape(-1, 2)).astype(np.int64)
    inside = np.all((rc >= 0) & (rc < np.asarray(shape)), axis=1)
    mask[rc[inside, 0], rc[inside, 1]] = True
    return mask


@dataclass(frozen=True)
class DarkFrame:
    """A dark frame and its hot pixels, or nothing (then :meth:`subtract` is the identity)."""

    frame: np.ndarray | None = None
    hot: np.ndarray | None = None

    @classmethod
    def of(cls, dark, shape) -> DarkFrame:
        """Check ``dark``: None, a DarkFrame, or a finite 2-D array of ``shape``.

        The hot pixels of an array are found here; a DarkFrame brings its own.
        """
        if dark is None:
            return cls()
        if isinstance(dark, DarkFrame):
            if dark.frame is not None and tuple(dark.frame.shape) != tuple(shape):
                raise ImageError(f"the dark frame has shape {dark.frame.shape}: expected the "
                                 f"sensor's {shape[0]} × {shape[1]} (rows × cols)")
            return dark
        d = np.asarray(dark)
        if d.ndim != 2 or tuple(d.shape) != tuple(shape):
            raise ImageError(f"the dark frame has shape {d.shape}: expected the sensor's "
                             f"{shape[0]} × {shape[1]} (rows × cols)")
        if not (np.issubdtype(d.dtype, np.integer) or np.issubdtype(d.dtype, np.floating)):
            raise ImageError(f"the dark frame's dtype {d.dtype} is not a real number type")
        d = d.astype(np.float32)
        if not np.isfinite(d).all():
            raise ImageError("the dark frame has NaN or infinite pixels: expected finite "
                             "counts")
        return cls(d, hot_pixels_from_dark(d))

    def subtract(self, image, *, patch: bool = False):
        """``image`` less the dark frame (float32), or ``image`` itself without one.

        ``patch``: also replace its hot pixels by the median of their neighbours
        (:func:`patch_pixels`; the spot detection does so itself, given ``hot``).
        """
        if self.frame is None:
            return image
        out = np.asarray(image, np.float32) - self.frame
        return patch_pixels(out, self.hot) if patch else out


#: The flat of the calibration images divides by the white down to this fraction of its lit
#: level and by that floor below it: the gain is continuous and at most ``1 / fraction``, so
#: the dim rims and gaps are never amplified into a ring that pulls the spots (a division
#: that zeroes or amplifies them without bound does).
WHITE_FLOOR_FRACTION = 0.5
#: Without a dark frame, a white's black level is this percentile of its pixels: its darkest
#: gaps (a white at the working aperture leaves a few per cent of the sensor between its
#: micro-images; its fixed pattern, a few counts under thousands, stays in the flat).
WHITE_BLACK_PERCENTILE = 1.0
#: The white's lit level: the median of its pixels above this fraction of its 99.9th
#: percentile (the micro-images' plateaus).
WHITE_LIT_FRACTION = 0.5


@dataclass(frozen=True)
class WhiteFlat:
    """The calibration images' flat field from a white, or nothing (:meth:`apply` identity).

    A white lights every micro-image through the camera's lenslets, so it holds each pixel's
    share of the light: the lenslets' throughput and the fall-off inside each micro-image
    (vignetting). The fall-off pulls every spot off its centre towards the brighter side,
    by its gradient times the spot's variance: an alignment spot off its micro-image's
    centre moves towards it, and the focal-point fit reads a longer S_i (+0.12 mm at 20 %
    light lost at the rims, docs/validation/realcam.md). Dividing by the white, pixel by
    pixel, takes the fall-off out.
    """

    gain: np.ndarray | None = None
    level: float = float("nan")
    black_pitch_px: float | None = None

    @classmethod
    def of(cls, white, dark: DarkFrame, shape, pitch_px: float) -> WhiteFlat:
        """The flat of ``white`` (None: none) less ``dark``; checked against ``shape``.

        Without a dark frame the white's black level (its :data:`WHITE_BLACK_PERCENTILE`
        percentile) is taken off it, and each image's own (:func:`black_level`, lenslet pitch
        ``pitch_px``) off the image before the flat multiplies it: a black level times the
        flat would print the micro-images into the gaps.
        """
        if white is None:
            return cls()
        from plenopiv.products.images import check_image

        w = dark.subtract(check_image(white, shape=shape, name="white image"), patch=True)
        w = np.asarray(w, dtype=np.float64)
        black_pitch = None
        if dark.frame is None:      # the white's black: its darkest gaps (a white has few)
            black_pitch = float(pitch_px)
            w = w - float(np.percentile(w, WHITE_BLACK_PERCENTILE))
        top = float(np.percentile(w, 99.9))
        lit = w > WHITE_LIT_FRACTION * top
        if not (top > 0 and lit.any()):
            raise ImageError("the white image holds no light above its dark: expected a "
                             "white at the working aperture")
        level = float(np.median(w[lit]))
        gain = level / np.maximum(w, WHITE_FLOOR_FRACTION * level)
        return cls(gain.astype(np.float32), level, black_pitch)

    def apply(self, image):
        """``image`` times the flat's gain (float32), or ``image`` itself without a white.

        Without a dark frame, the image's own black level is taken off first.
        """
        if self.gain is None or image is None:
            return image
        img = np.asarray(image, np.float32)
        if self.black_pitch_px is not None:
            img = img - black_level(img, self.black_pitch_px)
        return img * self.gain


def black_level(image, pitch_px: float) -> np.ndarray:
    """The black level of an image without its dark frame (float32, the image's shape).

    The smooth level of its dark gaps (per region of 4 x 4 pitches) plus the fixed pattern
    per column and row (:func:`fixed_pattern`; none on a white, whose gaps are too few).
    """
    a = np.asarray(image, dtype=np.float32)
    smooth, _ = _dark_gaps(a, pitch_px)
    return smooth + fixed_pattern(a, pitch_px)


def gap_level(image, pitch_px: float) -> tuple[float, float]:
    """An image's black level and its brightest light, counts.

    The median of its gaps' smooth level (:func:`black_level` without the pattern) and its
    99.9th percentile.
    """
    a = np.asarray(image, dtype=np.float32)
    smooth, _ = _dark_gaps(a, pitch_px)
    return float(np.median(smooth)), float(np.percentile(a[::2, ::2], 99.9))

