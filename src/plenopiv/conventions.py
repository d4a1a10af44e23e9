"""The coordinate conventions of plenopiv, written once; everything else converts through here.

Image space: optical axis z; the (thin) main lens at z = 0, image space z > 0 (towards the
sensor), object space z < 0.
Sensor: a pixel is ``(row, col)``, 0-based, the centre of the top-left pixel at (0, 0); images
are ``image[row, col]`` as read out, never flipped. Metric sensor coordinates (metres) have
their origin at the sensor centre, ``x = (col - (n_cols - 1)/2) * pixel_pitch``,
``y = (row - (n_rows - 1)/2) * pixel_pitch``; lenslet positions ``(s, t)`` share these axes.
Volume: ``(X, Y, Z)`` in metres; X, Y along the sensor's x, y (the image is inverted:
M = -S_i/S_o < 0); Z from the nominal focal plane, growing AWAY from the camera (in front of
the focal plane Z < 0). World points are ``(N, 3)`` arrays ``(x, y, z)``; volumes are indexed
``[z, y, x]``.
"""

from __future__ import annotations

import numpy as np


def pixel_to_sensor(rowcol, shape, pixel_pitch):
    """Convert pixel indices to metric sensor coordinates.

    Parameters
    ----------
    rowcol : array_like, shape (..., 2)
        Pixel positions ``(row, col)``, fractional allowed (pixel centres at integers).
    shape : tuple of int
        Sensor shape ``(n_rows, n_cols)``.
    pixel_pitch : float
        Pixel pitch in metres.

    Returns
    -------
    ndarray, shape (..., 2)
        Sensor coordinates ``(x, y)`` in metres, origin at the sensor centre.

    Examples
    --------
    >>> pixel_to_sensor([[0.0, 0.0]], (3, 5), 1.0)
    array([[-2., -1.]])
    """
    rc = np.asarray(rowcol, dtype=float)
    n_rows, n_cols = shape
    x = (rc[..., 1] - (n_cols - 1) / 2.0) * pixel_pitch
    y = (rc[..., 0] - (n_rows - 1) / 2.0) * pixel_pitch
    return np.stack([x, y], axis=-1)


def sensor_to_pixel(xy, shape, pixel_pitch):
    """Convert metric sensor coordinates ``(x, y)`` (metres) to fractional ``(row, col)``.

    The exact inverse of :func:`pixel_to_sensor`.
    """
    p = np.asarray(xy, dtype=float)
    n_rows, n_cols = shape
    col = p[..., 0] / pixel_pitch + (n_cols - 1) / 2.0
    row = p[..., 1] / pixel_pitch + (n_rows - 1) / 2.0
    return np.stack([row, col], axis=-1)


def volume_to_world_z(Z, object_distance):
    """Image-space-axis coordinate z (metres, < 0) of volume depth ``Z`` (metres).

    ``object_distance`` is the (air-equivalent) distance S_o from the main lens to the nominal
    focal plane; Z > 0 moves away from the camera, i.e. to more negative z.
    """
    return -(object_distance + np.asarray(Z, dtype=float))


def world_to_voxel(points, origin, voxel_size):
    """Convert world points ``(N, 3)`` ``(x, y, z)`` to fractional voxel indices ``(iz, iy, ix)``.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        ``(x, y, z)`` in metres (volume coordinates X, Y, Z).
    origin : array_like, shape (3,)
        ``(x, y, z)`` of the centre of voxel ``[0, 0, 0]``, metres.
    voxel_size : array_like, shape (3,) or float
        Voxel edge ``(dx, dy, dz)`` in metres.
    """
    p = np.asarray(points, dtype=float)
    v = (p - np.asarray(origin, dtype=float)) / np.asarray(voxel_size, dtype=float)
    return v[..., ::-1]


def voxel_to_world(index, origin, voxel_size):
    """Inverse of :func:`world_to_voxel`: ``(iz, iy, ix)`` to ``(x, y, z)`` metres."""
    i = np.asarray(index, dtype=float)[..., ::-1]
    return np.asarray(origin, dtype=float) + i * np.asarray(voxel_size, dtype=float)
