"""Per-vector standard uncertainty of a plenoptic PIV field: statistics plus the chain's response.

The correlation statistics cannot see an error both reconstructions share, and near the focal
plane a plenoptic camera has one. :func:`combine` adds to each vector's correlation
statistics (with the error the passes left, :func:`iteration_uncertainty`) what the chain's
measured response to known displacements says (:class:`plenopiv.piv.response.Response`, from
:func:`plenopiv.workflow.response.measure_response`): the excess random error, the error of
the gain, the bias of curvature inside a window (:func:`unresolved_gradient_bias`), the range
a rejected neighbour leaves open (:func:`rejected_neighbour_uncertainty`) and the error of the
vector's position (:func:`location_uncertainty`). The response is computed once per
experiment. See docs/methods.md#response-measurement for the terms and their reasons.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from plenopiv.piv.response import Response, vector_spacing
from plenopiv.piv.settings import UNCERTAINTY_METHODS

__all__ = [
    "UNCERTAINTY_METHODS",
    "combine",
    "location_uncertainty",
    "modulation_factor",
    "neighbourhood_max",
    "rejected_neighbour_uncertainty",
    "unresolved_gradient_bias",
]


MIN_GAIN = 0.1
"""Smallest gain the systematic term divides by (dimensionless)."""

DEFAULT_RATIO = 0.5
"""Convergence ratio of the passes where it cannot be measured (remaining error = last
correction)."""

MAX_CONVERGENCE_RATIO = 0.9
"""Largest convergence ratio counted: a ratio of 1 or more (no convergence) is held here, the
remaining error then nine times the last correction."""

CENTRAL_STENCIL = (1.0, -2.0, 1.0)
"""Second difference at an inner vector: its neighbours and itself (centred)."""

BORDER_STENCIL = (2.0, -5.0, 4.0, -1.0)
"""Second difference at a border vector, from itself inwards: one-sided and, like the
central one, of second order (exact for a cubic)."""


def _second_difference(a, axis):
    """Second difference of ``a`` along ``axis`` at every point (same shape, units of ``a``).

    Central ``a[i-1] - 2 a[i] + a[i+1]`` inside; at a border point of an axis of four or
    more points the one-sided ``2 a[0] - 5 a[1] + 4 a[2] - a[3]`` (``BORDER_STENCIL``: the
    curvature at that point, where the flow may curve more than one spacing inwards, not its
    neighbour's); with three points the only second difference there is; zero along an
    axis of fewer than 3 points.
    """
    a = np.moveaxis(np.asarray(a, float), axis, 0)
    out = np.zeros_like(a)
    if a.shape[0] >= 3:
        left, centre, right = CENTRAL_STENCIL
        out[1:-1] = left * a[:-2] + centre * a[1:-1] + right * a[2:]
        if a.shape[0] >= 4:
            out[0] = sum(c * a[j] for j, c in enumerate(BORDER_STENCIL))
            out[-1] = sum(c * a[-1 - j] for j, c in enumerate(BORDER_STENCIL))
        else:
            out[0] = out[-1] = out[1]
    return np.moveaxis(out, 0, axis)


def _stencil_weights(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The noise weights of :func:`_second_difference` per point of an axis of ``n`` points.

    Two arrays ``(n,)``, dimensionless: the weight the stencil at a point gives the point
    itself, and the sum of squares of the weights it gives the others.
    """
    own, others = np.zeros(n), np.zeros(n)
    if n >= 3:
        own[:], others[:] = CENTRAL_STENCIL[1], CENTRAL_STENCIL[0] ** 2 + CENTRAL_STENCIL[2] ** 2
        if n >= 4:
            own[[0, -1]] = BORDER_STENCIL[0]
            others[[0, -1]] = sum(c**2 for c in BORDER_STENCIL[1:])
        else:        # the middle point's stencil, which weights the border point by 1
            own[[0, -1]] = CENTRAL_STENCIL[0]
            others[[0, -1]] = CENTRAL_STENCIL[1] ** 2 + CENTRAL_STENCIL[2] ** 2
    return own, others


def _window_coefficients(spacing, window) -> np.ndarray:
    """``W_i^2 / (24 h_i^2)`` per axis ``(x, y, z)``, dimensionless.

    The window-average bias per unit second difference; 0 along an axis without spacing or
    window.
    """
    return np.array([float(w) ** 2 / (24.0 * float(h) ** 2) if float(h) > 0 and float(w) > 0
                     else 0.0 for h, w in zip(spacing, window, strict=True)])


def unresolved_gradient_bias(disp, spacing, window, scale=None):
    r"""Bias of window-averaged displacements where the displacement curves inside a window.

    Parameters
    ----------
    disp : ndarray, shape (3, nz, ny, nx)
        Measured displacement ``(u, v, w)`` on the vector grid, metres (NaN: no vector).
    spacing : sequence of 3 floats
        Vector spacing along ``(x, y, z)``, metres.
    window : sequence of 3 floats
        Window edge along ``(x, y, z)``, metres.
    scale : ndarray, shape (3, 3), optional
        Factor on the curvature of component ``k`` (rows ``u, v, w``) along axis ``a``
        (columns ``x, y, z``): :func:`modulation_factor` (None: 1).

    Returns
    -------
    ndarray, shape (3, nz, ny, nx)
        Magnitude of the estimated bias per component, metres; 0 where a second difference
        involves a missing vector.

    Notes
    -----
    A correlation window of edge :math:`W` weights the displacement in it about evenly (top
    hat), so it measures the window average rather than the value at its centre. Expanding
    the displacement to second order about the centre, the linear terms average out and

    .. math:: \bar u - u(0) = \sum_i \frac{1}{W_i}\int_{-W_i/2}^{W_i/2}
              \frac{x_i^2}{2}\,\partial_i^2 u \;dx_i
              = \sum_i \frac{W_i^2}{24}\, \partial_i^2 u .

    Window deformation removes part of it. A deformation pass moves the particles by the
    predictor :math:`P` (the previous vectors, trilinearly interpolated between vectors
    :math:`h` apart) and measures the window average of what is left, so at the iteration's
    fixed point :math:`d = P + \overline{u - P}`: the window averages of the flow's and of the
    predictor's curvature cancel, and only the mean error of the linear interpolation
    remains, :math:`-\sum_i (h_i^2/12)\, \partial_i^2 u` (half the one-window bias at 50 %
    overlap; ``tests/piv/test_uncertainty.py`` iterates the fixed point). A few passes do not
    reach it for curvature on the scale of the vector spacing (the errors of a vortex core
    follow the one-window bias of the true field, docs/validation/uncertainty.md), so the
    one-window bias is kept as the bound.

    The second derivatives are taken from the measured field's second differences on the
    vector grid, :math:`\partial_i^2 u \approx \Delta_i^2 u / h_i^2` (with 50 % overlap,
    :math:`W = 2h` and the term is :math:`\Delta_i^2 u / 6` per axis), central inside and
    one-sided at the border (:func:`_second_difference`): a border window reaches half a
    window beyond the last vectors, where the flow may curve more than one spacing inwards
    (a central stencil there would take the neighbour's curvature). A uniform or linear
    field gives zero; a quadratic or cubic one the exact curvature at every vector.
    """
    disp = np.asarray(disp, float)
    scale = np.ones((3, 3)) if scale is None else np.asarray(scale, float)
    coef = scale * _window_coefficients(spacing, window)[None, :]          # (component, axis)
    out = np.zeros_like(disp)
    for axis_xyz in range(3):
        if coef[:, axis_xyz].any():
            array_axis = 3 - axis_xyz      # (component, z, y, x): x is array axis 3
            out += coef[:, axis_xyz, None, None, None] * _second_difference(disp, array_axis)
    return np.abs(np.nan_to_num(out, nan=0.0))


def modulation_factor(modulation, spacing, window) -> np.ndarray:
    r"""What the measured curvature misses of the window's bias, ``(3, 3)``, dimensionless.

    Parameters
    ----------
    modulation : ndarray, shape (3, 3)
        The chain's gain :math:`H_{ka}` of component ``k`` for a sinusoidal displacement
        along axis ``a`` of ``MODULATION_PERIOD`` = 4 vector spacings
        (:attr:`plenopiv.piv.response.Response.modulation`; NaN: not measured).
    spacing, window : sequence of 3 floats
        Vector spacing and window edge along ``(x, y, z)``, metres.

    Returns
    -------
    ndarray, shape (3, 3)
        :math:`F_{ka} = \max\big(1, (1 - H_{ka}) / (2 c_a H_{ka})\big)` with
        :math:`c_a = W_a^2 / (24 h_a^2)` and :math:`H` held within ``[MIN_GAIN, 1]``; 1 where
        :math:`H` is not measured or the axis has no spacing.

    Notes
    -----
    :func:`unresolved_gradient_bias` takes the curvature from the measured field, which the
    windows have already flattened: where the flow curves on the scale of a window (Hill's
    core) the measured curvature, and with it the bias, is short by the chain's own loss of
    modulation. A wave :math:`A \sin(k x_a)` of wavelength :math:`4 h_a` is measured as
    :math:`H A \sin(k x_a)`, an error of :math:`(1 - H) A`; its second difference on the
    vector grid is :math:`-2 H A \sin(k x_a)`, so the bias term gives :math:`2 c_a H A`.
    ``F`` makes the term the error at that wavelength. For a top-hat window at 50 % overlap
    (:math:`H = 2/\pi`, :math:`c = 1/6`) it is 1.71; for longer waves the bias the
    curvature gives approaches the true one (``F`` = 1 in the limit), so ``F`` is the
    bound over the wavelengths the vector grid resolves. ``H`` is measured, not modelled:
    window deformation and the reconstruction change it from the top hat's.
    """
    out = np.ones((3, 3))
    if modulation is None:
        return out
    h = np.clip(np.nan_to_num(np.asarray(modulation, float), nan=1.0), MIN_GAIN, 1.0)
    for a, c in enumerate(_window_coefficients(spacing, window)):
        if c > 0:
            out[:, a] = np.maximum(1.0, (1.0 - h[:, a]) / (2.0 * c * h[:, a]))
    return out


def curvature_noise_factor(spacing, window, scale=None, shape=None):
    r"""Variance of :func:`unresolved_gradient_bias` from vectors' random errors, per unit variance.

    Parameters
    ----------
    spacing, window : sequence of 3 floats
        Vector spacing and window edge along ``(x, y, z)``, metres (as for
        :func:`unresolved_gradient_bias`).
    scale : ndarray, shape (3, 3), optional
        The factors of :func:`unresolved_gradient_bias` (None: 1).
    shape : tuple (nz, ny, nx), optional
        The vector grid: the factor of every vector, its border ones included.

    Returns
    -------
    float or ndarray, shape (3,) or (3, nz, ny, nx)
        At an inner vector :math:`k = 2 \sum_i a_i^2 + 4 (\sum_i a_i)^2` with
        :math:`a_i = W_i^2 / (24 h_i^2)` (dimensionless; 7/6 at 50 % overlap in 3-D); with
        ``scale``, per component ``k`` with :math:`a_i` times ``scale[k, i]``; with ``shape``,
        per component and vector.

    Notes
    -----
    The bias term is :math:`\sum_i a_i \sum_j s_{ij} d_j`, with :math:`s_i` the stencil of
    :func:`_second_difference` along axis ``i``. Vectors with independent random errors of
    variance :math:`\sigma^2` give it the variance :math:`\sigma^2 [(\sum_i a_i s_{i0})^2 +
    \sum_i a_i^2 \sum_{j \ne 0} s_{ij}^2]`, the vector itself with the sum of its weights
    and every other point with its own. Inside, :math:`s = (1, -2, 1)` gives the formula
    above (the six neighbours once each, the centre with :math:`-2 \sum_i a_i`): the
    estimate of a curvature from noisy vectors is about as large as their noise where the
    field does not curve at all. The one-sided border stencil :math:`(2, -5, 4, -1)`
    carries 7.7 times the noise of the central one. That noise is the vectors' random
    error, already counted; :func:`combine` removes its variance.
    """
    a = _window_coefficients(spacing, window)
    a = (np.ones((3, 3)) if scale is None else np.asarray(scale, float)) * a[None, :]
    if shape is None:
        k = 2.0 * np.sum(a**2, axis=1) + 4.0 * np.sum(a, axis=1) ** 2
        return float(k[0]) if scale is None else k
    own = np.zeros((3,) + tuple(shape))
    others = np.zeros((3,) + tuple(shape))
    for axis_xyz, n in enumerate(tuple(shape)[::-1]):
        weight_self, weight_others = _stencil_weights(n)
        along = [1, 1, 1]
        along[2 - axis_xyz] = n           # (z, y, x): x is array axis 2
        coef = a[:, axis_xyz].reshape(3, 1, 1, 1)
        own = own + coef * weight_self.reshape(along)
        others = others + coef**2 * weight_others.reshape(along)
    return own**2 + others


def filter_offset(disp):
    r"""The change a converged pass still makes with the smoothed predictor, units of ``disp``.

    Parameters
    ----------
    disp : ndarray, shape (3, nz, ny, nx)
        Displacement on the vector grid (any unit; NaN counts as 0).

    Returns
    -------
    ndarray, shape (3, nz, ny, nx)
        :math:`d - S(d)`, with :math:`S` the predictor's binomial filter ``[1, 2, 1] / 4``
        per axis (:func:`plenopiv.piv.outliers._smooth_predictor`).

    Notes
    -----
    A deformation pass correlates the volumes deformed by the smoothed predictor
    :math:`S(d_{k-1})` and adds the corrector it measures: :math:`d_k = S(d_{k-1}) + c_k`.
    At the iteration's fixed point :math:`d_k = d_{k-1} = d` the corrector is still
    :math:`c = d - S(d) \approx -\sum_i \Delta_i^2 d / 4`, nonzero wherever the field
    curves, although the estimate no longer changes. This part of the last correction is
    the filter's offset, not an error left by the iteration; the window-average bias of
    the same curvature is :func:`unresolved_gradient_bias`.
    """
    from plenopiv.piv.outliers import _smooth_predictor

    d = np.nan_to_num(np.asarray(disp, float), nan=0.0)
    return d - _smooth_predictor(d)


def convergence_ratio(last, previous, usable, noise=None) -> np.ndarray:
    r"""Measured ratio of the last two corrections per component, ``(3,)``, dimensionless.

    Parameters
    ----------
    last, previous : ndarray, shape (3, nz, ny, nx)
        The last and the previous pass's corrections, the filter offset removed (metres).
    usable : ndarray of bool, shape (nz, ny, nx)
        Vectors to count (valid, finite in both).
    noise : ndarray, shape (3, nz, ny, nx), optional
        The random error of one pass's correction, metres: the correlation statistics
        (None: no noise, the ratio of the corrections as they are).

    Returns
    -------
    ndarray, shape (3,)
        :math:`\rho_k = \sqrt{(\langle c_{n,k}^2 \rangle - \langle \sigma_k^2 \rangle)
        / (\langle c_{n-1,k}^2 \rangle - \langle \sigma_k^2 \rangle)}` over the usable
        vectors, within ``[0, MAX_CONVERGENCE_RATIO]``: 0 where the last corrections are no
        larger than their noise, ``MAX_CONVERGENCE_RATIO`` where only the last ones exceed
        it; ``DEFAULT_RATIO`` for a component without usable vectors or without a previous
        change.

    Notes
    -----
    The passes converge geometrically when each removes a fraction :math:`1 - \rho` of the
    error it starts from: :math:`e_n = \rho\, e_{n-1}`, so the corrections shrink by the same
    factor, :math:`c_n = e_n - e_{n-1} = \rho\, c_{n-1}`, and what the last pass left is
    :math:`e_n = \rho / (1 - \rho)\; c_n` (:func:`iteration_uncertainty`). The ratio is
    taken over the whole field (a few hundred vectors: a local ratio of two noisy corrections
    would be unstable).

    Each correction also holds the random error of its correlation, which does not shrink
    from pass to pass: once the iteration has converged the corrections are that noise
    alone, and their ratio tends to 1 (a tail of nine times the noise at the cap) although
    nothing is left to correct. The noise adds in quadrature to the systematic change, so
    its variance (the correlation statistics, counted in the uncertainty on their own) is
    removed from both mean squares before the ratio is taken: a last correction within its
    noise gives a ratio of 0, as the passes that have converged to their noise do on the
    vortex validations (docs/validation/uncertainty.md).
    """
    out = np.full(3, DEFAULT_RATIO)
    if previous is None:
        return out
    for k in range(3):
        a, b = last[k][usable], previous[k][usable]
        n2 = np.zeros_like(a) if noise is None else np.asarray(noise[k], float)[usable] ** 2
        ok = np.isfinite(a) & np.isfinite(b) & np.isfinite(n2)
        if not ok.any():
            continue
        noise2 = float(np.mean(n2[ok]))
        num = float(np.mean(a[ok] ** 2)) - noise2
        den = float(np.mean(b[ok] ** 2)) - noise2
        if num <= 0.0 and (noise is not None or den > 0.0):
            out[k] = 0.0
        elif den > 0.0:
            out[k] = min(np.sqrt(num / den), MAX_CONVERGENCE_RATIO)
        elif num > 0.0:
            out[k] = MAX_CONVERGENCE_RATIO
    return out


def iteration_uncertainty(field) -> np.ndarray | None:
    r"""Correlation statistics and the error the iteration left, ``(3, nz, ny, nx)``, metres.

    :math:`\sqrt{\sigma_{CS}^2 + (\rho / (1 - \rho))^2\, \max(0, (c_n - o)^2 - \sigma_{CS}^2)}`
    per component, with :math:`\sigma_{CS}` the correlation statistics, :math:`c_n` the last
    pass's correction, :math:`o` the filter's offset (:func:`filter_offset`; zero without a
    smoothed predictor) and :math:`\rho` the measured ratio of the last two corrections, their
    noise removed (:func:`convergence_ratio`; 1/2, i.e. the remaining error as large as the
    last correction, when the previous pass had other windows). The random error of the
    last correction is the correlation's, which :math:`\sigma_{CS}` counts already: only the
    part of the correction above it is a change the iteration was still making.
    A rejected vector keeps the uncertainty :func:`plenopiv.piv.correlate_volumes` gave it
    (its neighbours' uncertainty and spread). None when ``field`` carries no signed
    corrections (then its own uncertainty stands).
    """
    parts = field.uncertainty_parts or {}
    if "last_corrector" not in parts or "correlation" not in parts:
        return None
    disp = np.stack([field.u, field.v, field.w])
    smoothed = bool(getattr(field.settings, "smooth_predictor", False))
    offset = filter_offset(disp) if smoothed else np.zeros_like(disp)
    noise = np.asarray(parts["correlation"], float)
    last = np.asarray(parts["last_corrector"], float) - offset
    previous = parts.get("previous_corrector")
    if previous is not None:
        previous = np.asarray(previous, float) - offset
    usable = np.asarray(field.valid, bool) & np.all(np.isfinite(disp), axis=0)
    rho = convergence_ratio(last, previous, usable, noise)
    systematic = np.sqrt(np.maximum(np.nan_to_num(last) ** 2 - np.nan_to_num(noise) ** 2, 0.0))
    remaining = (rho / (1.0 - rho))[:, None, None, None] * systematic
    sigma = np.sqrt(noise**2 + remaining**2)
    own = np.stack([field.u_uncertainty, field.v_uncertainty, field.w_uncertainty])
    return np.where(np.asarray(field.valid, bool)[None], sigma, own)


def neighbourhood_max(a) -> np.ndarray:
    """The largest value of ``a`` over each point's 3 x 3 x 3 neighbourhood, itself included.

    The neighbourhood of the median test; points beyond the grid count as 0 (False).
    ``a`` is ``(nz, ny, nx)``, numeric or bool; the result has its shape and dtype.
    """
    import scipy.ndimage

    return scipy.ndimage.maximum_filter(np.asarray(a), size=3, mode="constant", cval=0)


REJECTED_RANGE_FACTOR = 1.0 / np.sqrt(12.0)
"""Standard deviation of a rectangular distribution over a range, per unit of its width."""


def rejected_neighbour_uncertainty(field, spurious=None) -> np.ndarray:
    r"""Uncertainty of vectors beside a rejected one, ``(3, nz, ny, nx)``, metres.

    Parameters
    ----------
    field : VectorField
        A field of :func:`plenopiv.piv.correlate_volumes`; its ``uncertainty_parts`` hold
        ``"rejected_disagreement"``, how far each rejected vector's own measurement lay from
        the median of its neighbours (0 for vectors that were not rejected).
    spurious : ndarray, shape (3,), optional
        The reach of a spurious correlation peak per component, metres
        (:attr:`plenopiv.piv.response.Response.spurious`; None: 0).

    Returns
    -------
    ndarray, shape (3, nz, ny, nx)
        :math:`\max_j \sqrt{\max(0, D_{j,k}^2 - S_k^2)} / \sqrt{12}` per component ``k``
        (:math:`S` = ``spurious``) over the rejected vectors
        ``j`` of the vector's 3 x 3 x 3 neighbourhood (itself included), metres; 0 where none
        was rejected or the field carries no disagreements.

    Notes
    -----
    The median test rejects a vector whose measurement :math:`m_j` disagrees with the median
    :math:`\tilde m_j` of its neighbours by more than their noise allows; it cannot tell a
    spurious correlation peak from a flow that changes faster than the vector spacing
    resolves. Where a flow reverses within about one window (the core of Hill's vortex) the
    rejected vectors are mostly the ones that saw the reversal, and their neighbours, whose
    windows overlap theirs by half, carry errors of the same order that no other term sees
    (docs/validation/uncertainty.md). Between the two readings the displacement near the
    rejected vector is known only to lie in the range :math:`D_j = |m_j - \tilde m_j|`; with
    nothing to prefer a value within it, a rectangular distribution over the range (GUM
    4.3.7) has the standard deviation :math:`D_j / \sqrt{12}`, counted for the rejected
    vector and each vector of its 3 x 3 x 3 neighbourhood (the neighbourhood of the median
    test), the largest where several apply. A field without rejected vectors gets 0.

    The median test also rejects spurious peaks (a ghost particle, an unmatched pair, the
    depth peak's elongated neighbour), whose disagreement says nothing about the flow
    around them: the vectors beside one err as the response's test vectors do beside
    theirs, which their spread counts already. The rejected vectors of the uniform test
    pairs, where no flow is left unresolved, give the reach :math:`S_k` of such peaks
    (:func:`plenopiv.piv.response.spurious_disagreement`, their median); only the part of a
    disagreement beyond it, in quadrature, is counted as unresolved flow. Where a flow
    reverses laterally within a window while its depth readings beside the core are spurious
    peaks along the elongated depth axis, the rejected vectors' lateral disagreements stand
    far above the test pairs' and their depth ones do not; counted in full, the depth
    readings would overstate the vectors' depth error several times
    (docs/validation/uncertainty.md).
    """
    parts = field.uncertainty_parts or {}
    jump = parts.get("rejected_disagreement")
    shape = np.shape(field.u)
    if jump is None:
        return np.zeros((3,) + shape)
    jump = np.nan_to_num(np.asarray(jump, float))
    if spurious is not None:
        reach = np.nan_to_num(np.asarray(spurious, float)).reshape(3, 1, 1, 1)
        jump = np.sqrt(np.maximum(jump**2 - reach**2, 0.0))
    return REJECTED_RANGE_FACTOR * np.stack([neighbourhood_max(jump[k]) for k in range(3)])


def location_uncertainty(disp, spacing, offset) -> np.ndarray:
    r"""Error of a vector reported at its window's centre while it measured elsewhere.

    Parameters
    ----------
    disp : ndarray, shape (3, nz, ny, nx)
        The measured displacement ``(u, v, w)``, metres (NaN where none).
    spacing : sequence of 3 floats
        Vector spacing along ``(x, y, z)``, metres (0 along an axis with one vector).
    offset : ndarray, shape (3, nz)
        The reconstruction's placement offset per axis ``(x, y, z)`` and layer, metres
        (:meth:`plenopiv.piv.response.Response.location`).

    Returns
    -------
    ndarray, shape (3, nz, ny, nx)
        :math:`\sqrt{\sum_a (\partial d_k / \partial x_a\, \delta_a)^2}` per component
        ``k``, metres; 0 where a derivative is undefined (beside a NaN vector).

    Notes
    -----
    The window at centre ``c`` holds particles the reconstruction placed there, whose true
    positions lie around ``c - δ``; the vector is the displacement at ``c - δ``, reported at
    ``c``. The error is the change of the displacement over δ, ``-δ · ∇d`` to first order
    (GUM 5.1.3: the sensitivity coefficient of the position, here the measured field's
    gradient, central differences between vectors). The uniform test displacements of the
    response have no gradient and cannot show it; a component that changes sign across the
    depth of a volume beyond the focal plane is under-covered without it
    (docs/validation/uncertainty.md).
    """
    disp = np.asarray(disp, float)
    offset = np.nan_to_num(np.asarray(offset, float))
    out = np.zeros_like(disp)
    for k in range(3):
        for axis, (step, delta) in enumerate(zip(spacing, offset, strict=True)):
            array_axis = 2 - axis                   # x, y, z -> array axes 2, 1, 0
            if step <= 0 or disp.shape[1 + array_axis] < 2:
                continue
            slope = np.gradient(disp[k], step, axis=array_axis)
            out[k] += np.nan_to_num(slope * delta[:, None, None]) ** 2
    return np.sqrt(out)


def _spacing_and_window(field):
    """Vector spacing and last-pass window edge along ``(x, y, z)``, metres."""
    settings = field.settings
    window_vox = settings.window_vox(settings.passes - 1)[::-1]     # (wx, wy, wz)
    spacing = vector_spacing(field)
    step_vox = np.array([max(1, round(w * (1.0 - settings.overlap))) for w in window_vox])
    return spacing, np.asarray(window_vox, float) * spacing / step_vox


def combine(field, response: Response | None):
    """The field with its uncertainties completed by the chain's response (module notes).

    ``field`` is a :class:`~plenopiv.piv.VectorField` (effective coordinates) whose
    ``u_uncertainty`` etc. hold the correlation statistics; ``response`` None returns it as
    is. Vectors without a displacement (NaN) keep NaN.
    """
    if response is None:
        return field
    disp = np.stack([field.u, field.v, field.w])
    sigma_cs = iteration_uncertainty(field)
    if sigma_cs is None:
        sigma_cs = np.stack([field.u_uncertainty, field.v_uncertainty, field.w_uncertainty])
    excess = response.excess(field.z, disp)
    sigma_gain = response.gain_error(field.z, MIN_GAIN)[:, :, None, None] * np.abs(disp)
    spacing, window = _spacing_and_window(field)
    parts = dict(field.uncertainty_parts or {})
    # the curvature estimate less the part the vectors' random errors give it (counted by
    # the correlation statistics and the response's excess already)
    random = parts.get("correlation")
    random = (np.zeros_like(disp) if random is None
              else np.nan_to_num(np.asarray(random, float))) ** 2 + excess**2
    scale = modulation_factor(response.modulation, spacing, window)
    sigma_curv = np.sqrt(np.maximum(
        unresolved_gradient_bias(disp, spacing, window, scale) ** 2
        - curvature_noise_factor(spacing, window, scale, disp.shape[1:]) * random, 0.0))
    sigma_rejected = rejected_neighbour_uncertainty(field, response.spurious)
    sigma_location = location_uncertainty(disp, spacing, response.location(field.z))
    total = np.sqrt(sigma_cs**2 + excess**2 + sigma_gain**2 + sigma_curv**2
                    + sigma_rejected**2 + sigma_location**2)
    parts["response_random"] = excess
    parts["response_gain"] = sigma_gain
    parts["unresolved_gradient"] = sigma_curv
    parts["rejected_neighbour"] = sigma_rejected
    parts["location"] = sigma_location
    return replace(field, u_uncertainty=total[0], v_uncertainty=total[1],
                   w_uncertainty=total[2], uncertainty_parts=parts)
