"""Geometric optics of the plenoptic camera: matrices, thin lens, distances, focal spots.

Ray transfer matrices, thin-lens relations, effective (air-equivalent) distances, focal-spot
relations and calibration uncertainties.

All lengths in metres, angles in radians. Equation numbers refer to the thesis
"Determination of the Image Distance in a Plenoptic Camera" (docs/design.md), with the misprint of
its Eq. 4.9 corrected: the effective image distance is S_i,eff = l3 + t/n (Eq. 4.4, as the
thesis's own §5.1 numbers confirm), not l3 + n t.
"""

from __future__ import annotations

import math

import numpy as np

from plenopiv.errors import ConfigError

# --------------------------------------------------------------------------------------------
# Ray transfer (ABCD) matrices acting on (height x, angle θ)
# --------------------------------------------------------------------------------------------


def propagation(distance):
    """Free propagation over ``distance`` (metres): ``[[1, d], [0, 1]]``."""
    return np.array([[1.0, float(distance)], [0.0, 1.0]])


def thin_lens(focal_length):
    """Thin lens of focal length ``focal_length`` (metres): ``[[1, 0], [-1/f, 1]]``."""
    return np.array([[1.0, 0.0], [-1.0 / float(focal_length), 1.0]])


def flat_interface(n_in, n_out):
    """Paraxial refraction at a flat interface from index ``n_in`` into ``n_out``.

    Snell's law for small angles, n_in θ_in = n_out θ_out, gives ``[[1, 0], [0, n_in/n_out]]``
    (thesis Eq. 4.2).
    """
    return np.array([[1.0, 0.0], [0.0, float(n_in) / float(n_out)]])


def system_matrix(*elements):
    """Compose ray transfer matrices given in the order the ray meets them."""
    m = np.eye(2)
    for e in elements:
        m = np.asarray(e, dtype=float) @ m
    return m


# --------------------------------------------------------------------------------------------
# Thin-lens relations (Eqs. 3.1-3.4)
# --------------------------------------------------------------------------------------------


def conjugate_distance(focal_length, distance):
    """The conjugate of ``distance`` through a thin lens: 1/S_o + 1/S_i = 1/f (Eq. 3.1)."""
    return 1.0 / (1.0 / focal_length - 1.0 / np.asarray(distance, dtype=float))


def magnification(image_distance, object_distance):
    """M = -S_i/S_o (Eq. 3.2); negative for a real, inverted image."""
    return -np.asarray(image_distance, dtype=float) / np.asarray(object_distance, dtype=float)


def image_distance_from_magnification(focal_length, magnification):
    """S_i = f_m (1 - M) (Eq. 3.4), metres."""
    return focal_length * (1.0 - np.asarray(magnification, dtype=float))


def object_distance_from_magnification(focal_length, magnification):
    """S_o = f_m (M - 1)/M (Eq. 3.3), metres."""
    m = np.asarray(magnification, dtype=float)
    return focal_length * (m - 1.0) / m


# --------------------------------------------------------------------------------------------
# Effective (air-equivalent) distances (Eqs. 4.3, 4.4; Table 4.1)
# --------------------------------------------------------------------------------------------


def effective_image_distance(l3, thickness, refractive_index):
    """S_i,eff = l3 + t/n (Eq. 4.4; the printed Eq. 4.9 ``l3 + n t`` is a misprint).

    >>> round(effective_image_distance(95.68e-3, 6.3e-3, 1.46) * 1e3, 2)
    100.0
    """
    return l3 + thickness / refractive_index


def physical_plate_distance(image_distance_eff, thickness, refractive_index):
    """l3 = S_i,eff - t/n: air path from the main lens to the plate, metres."""
    return image_distance_eff - thickness / refractive_index


def effective_object_distance(l2, medium_depth, n_medium, n_outside=1.0):
    """S_o,eff = l2 + (n2/n1) l1 (Eq. 4.3), metres.

    >>> round(effective_object_distance(69.92e-3, 40e-3, 1.33) * 1e3, 2)
    100.0
    """
    return l2 + (n_outside / n_medium) * medium_depth


def physical_interface_distance(object_distance_eff, medium_depth, n_medium, n_outside=1.0):
    """l2 = S_o,eff - (n2/n1) l1: air path from the main lens to the interface, metres."""
    return object_distance_eff - (n_outside / n_medium) * medium_depth


# --------------------------------------------------------------------------------------------
# Focal spots (Eqs. 3.11, 4.8), paraxial and exact chief ray
# --------------------------------------------------------------------------------------------

BACK_SIDES = ("physical", "thesis")


def _check_back_side(back_side):
    if back_side not in BACK_SIDES:
        raise ConfigError(f"back_side = {back_side!r}: expected one of {BACK_SIDES}")


def focal_spot_scale(image_distance_eff, sensor_distance, *, back_side="physical",
                     thickness=0.0, refractive_index=1.0, pupil_offset=0.0):
    """Paraxial ratio p/d of focal spot to lenslet centre (both from the optical axis).

    Parameters
    ----------
    image_distance_eff : float or ndarray
        S_i,eff, metres.
    sensor_distance : float
        f̄, lenslet plane to sensor, metres.
    back_side : {"physical", "thesis"}
    thickness, refractive_index : float
        Substrate t (metres) and n; t = 0 for none.
    pupil_offset : float
        Exit pupil position e relative to the thin-lens plane, metres (+ towards the sensor);
        chief rays start at (0, 0, e).

    Notes
    -----
    physical (Eq. 3.11 with the effective distance): ``p/d = 1 + f̄/(S_i,eff - e)``.

    thesis (Eq. 4.8, Appendix B): the ray keeps its in-glass angle down to the sensor,
    ``p/d = 1 + f̄/(n l3' + t)`` with ``l3' = S_i,eff - t/n - e`` the air path from the pupil
    to the plate.
    """
    _check_back_side(back_side)
    si = np.asarray(image_distance_eff, dtype=float)
    if back_side == "physical":
        return 1.0 + sensor_distance / (si - pupil_offset)
    n, t = refractive_index, thickness
    l3 = si - t / n - pupil_offset
    return 1.0 + sensor_distance / (n * l3 + t)


def image_distance_from_spot_scale(scale, sensor_distance, *, back_side="physical",
                                   thickness=0.0, refractive_index=1.0, pupil_offset=0.0):
    """Invert :func:`focal_spot_scale`: S_i,eff (metres) from the measured p/d."""
    _check_back_side(back_side)
    k = np.asarray(scale, dtype=float) - 1.0
    if back_side == "physical":
        return sensor_distance / k + pupil_offset
    n, t = refractive_index, thickness
    l3 = (sensor_distance / k - t) / n
    return l3 + t / n + pupil_offset


def chief_ray_tangent(rho, air_path, thickness, n, iterations=30):
    """Tangent of the ray crossing ``rho`` over air ``air_path`` then ``thickness`` of index n.

    Solves rho = a tanθ + t tan(asin(sinθ/n)) by Newton's method, vectorised (metres).
    """
    rho = np.asarray(rho, dtype=float)
    if thickness == 0.0:
        return rho / air_path
    m = rho / (air_path + thickness / n)  # paraxial start
    for _ in range(iterations):
        s = m / np.sqrt(1.0 + m * m)               # sin θ
        sg = s / n                                 # sin θ_glass
        cg = np.sqrt(1.0 - sg * sg)
        tg = sg / cg                               # tan θ_glass
        f = air_path * m + thickness * tg - rho
        # d(sinθ)/dm = (1+m²)^(-3/2); d(tanθg)/d(sinθg) = 1/cg³
        dtg = (1.0 / n) * (1.0 + m * m) ** -1.5 / cg ** 3
        step = f / (air_path + thickness * dtg)
        m = m - step
        if np.all(np.abs(step) < 1e-16):
            break
    return m


def _disc_quadrature():
    """Return points (unit disc) and weights of a symmetric disc quadrature.

    Exact for polynomials of degree 5 in r^2 and trigonometric degree 7: 3 Gauss-Legendre
    nodes in r^2 times 8 angles (24 points).
    """
    u, w = np.polynomial.legendre.leggauss(3)
    u, w = 0.5 * (u + 1.0), 0.5 * w
    phi = 2.0 * np.pi * (np.arange(8) + 0.5) / 8.0
    r = np.sqrt(u)[:, None]
    pts = np.stack([(r * np.cos(phi)).ravel(), (r * np.sin(phi)).ravel()], axis=1)
    return pts, np.repeat(w / 8.0, 8)


def focal_spot_exact(centres, image_distance_eff, sensor_distance, *, back_side="physical",
                     thickness=0.0, refractive_index=1.0, pupil_offset=0.0, stop_radius=0.0):
    """Return where the exact chief ray through each lenslet centre meets the sensor.

    With a stop radius: the centroid of the whole spot instead.

    The chief ray leaves the exit-pupil centre (0, 0, e), refracts exactly (Snell, not
    paraxial) into the substrate, passes the lenslet centre undeviated and reaches the sensor
    a distance f̄ behind the lenslet plane: in air ("physical") or at its in-glass angle
    ("thesis").

    Parameters
    ----------
    centres : array_like, shape (N, 2)
        Lenslet centres ``(s, t)`` in metres from the optical axis.
    image_distance_eff, sensor_distance, back_side, thickness, refractive_index, pupil_offset
        As in :func:`focal_spot_scale`.
    stop_radius : float
        Radius of the stop (at the exit pupil) the spot's light came through, metres. 0 (the
        default): the chief ray, the thesis's model. Otherwise the mean landing point of the
        rays from the whole stop through the lenslet centre (a 24-point disc quadrature):
        the spot's centroid. Through a plate the ray's slope is not linear in its pupil
        point, so the centroid sits off the chief ray by a fraction of order
        ``(stop_radius / S_i)^2`` of the spot's displacement: with the "thesis" back side at
        f/16 and S_i = 145 mm the chief-ray model reads S_i 0.03 mm long.

    Returns
    -------
    ndarray, shape (N, 2)
        Sensor positions ``(x, y)`` in metres.
    """
    _check_back_side(back_side)
    d = np.asarray(centres, dtype=float)
    n, t = float(refractive_index), float(thickness)
    air = image_distance_eff - t / n - pupil_offset   # pupil -> plate (or lenslets)
    if stop_radius > 0 and (t > 0 or back_side == "thesis"):
        q, w = _disc_quadrature()
        out = np.zeros_like(d)
        for (px, py), wk in zip(q * float(stop_radius), w, strict=True):
            out += wk * _spot_offset(d - np.array([px, py]), air, t, n, back_side,
                                     sensor_distance)
        return d + out
    return d + _spot_offset(d, air, t, n, back_side, sensor_distance)


def _spot_offset(v, air, t, n, back_side, sensor_distance):
    """f̄ times the slope vector behind the lenslets of the ray crossing ``v`` (N, 2), m."""
    rho = np.hypot(v[:, 0], v[:, 1])
    m = chief_ray_tangent(rho, air, t, n)
    if back_side == "physical":
        slope = m
    else:
        s = m / np.sqrt(1.0 + m * m) / n
        slope = s / np.sqrt(1.0 - s * s)
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.where(rho > 0, sensor_distance * slope / np.where(rho > 0, rho, 1.0), 0.0)
    return v * k[:, None]


# --------------------------------------------------------------------------------------------
# Magnification-method uncertainty (Eqs. 3.5-3.10)
# --------------------------------------------------------------------------------------------


def depth_of_focus(focal_length, f_number, magnification, lenslet_pitch, object_distance):
    """Front and back depth of focus L1, L2 (metres) of the nominal focal plane.

    Notes
    -----
    Eqs. 3.5-3.7: ``C = p_m/|M|`` (circle of confusion on the object side: one lenslet),
    ``d = f_m/N`` (aperture diameter), ``L1 = C S_o/(d + C)``, ``L2 = C S_o/(d - C)``.
    """
    c = lenslet_pitch / abs(magnification)
    d = focal_length / f_number
    if c >= d:
        raise ConfigError(f"circle of confusion C = {c * 1e3:.4g} mm is not smaller than the "
                          f"aperture d = {d * 1e3:.4g} mm: the depth of focus is unbounded")
    return c * object_distance / (d + c), c * object_distance / (d - c)


def magnification_method_uncertainty(focal_length, f_number, image_distance, lenslet_pitch):
    """Depth-of-focus uncertainty ΔS_i (metres) of the magnification method.

    Notes
    -----
    Eq. 3.9 with the span of the depth of focus L1 + L2: ``ΔS_i = M² (L1 + L2)``. (Eq. 3.8 as
    printed, C²S_o/(d² + C²), does not reproduce the thesis's ≈ 1 % of S_i of Fig. 3.5;
    L1 + L2 does: ≈ 2 p_m N / f_m · S_i, i.e. 1.04 % for a 135 mm lens at f/5.6.)

    >>> round(magnification_method_uncertainty(0.135, 5.6, 0.2, 125e-6) / 0.2 * 100, 2)
    1.04
    """
    so = float(conjugate_distance(focal_length, image_distance))
    m = -image_distance / so
    l1, l2 = depth_of_focus(focal_length, f_number, m, lenslet_pitch, so)
    return m * m * (l1 + l2)


def height_error_sensitivity(focal_length, object_span):
    """ΔS_i/Δd_i = f_m/d_o (Eq. 3.10): image-distance error per image-height error.

    >>> round(height_error_sensitivity(0.135, 0.01) * 125e-6 * 1e3, 2)   # mm for one lenslet
    1.69
    """
    return focal_length / object_span


def max_field_angle(camera) -> float:
    """Largest chief-ray angle (radians) to a lenslet centre, for sanity checks."""
    c = camera.microlens_array.centres()
    return math.atan(np.hypot(c[:, 0], c[:, 1]).max() / camera.image_distance)
