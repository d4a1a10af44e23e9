"""Numerical kernels of :mod:`plenopiv.piv`, each a numba function with its plain-NumPy twin.

Every kernel takes arrays and scalars only and returns new arrays; only ``cross_spectrum``
writes into an ``out`` array its caller passes (possibly one of its inputs, a scratch buffer).
The two implementations of a kernel share one signature and one meaning; the tests run both
on the same inputs and :func:`plenopiv.piv.correlate_volumes` chooses one by its ``engine``
argument (``"numba"``, the default, or ``"numpy"``). All positions, shifts and displacements
here are in voxels and in the volume's index order ``(z, y, x)``.

Kernels
-------
extract_windows
    Copy interrogation windows at arbitrary start voxels out of a volume (zero outside it).
cross_spectrum
    From the real-FFT spectra ``A, B`` of ``p * q`` windows, laid out ``(kz, p, ky, q, kx)``
    as the staged transform of :mod:`plenopiv.piv` leaves them (``nx`` is the real window
    length along x): the cross spectrum ``conj(A) B`` without its mean (DC) term, written
    into ``out`` shaped ``(p, q, kz, ky, kx)``, and per window (Parseval's theorem) the
    energies about the mean ``sum((a - mean(a))**2)``, ``sum((b - mean(b))**2)`` and the
    total energies ``sum(a**2)``, ``sum(b**2)``, returned as the columns of an (n, 4) array.
find_peaks
    For a batch of circular correlation planes: the displacement (n, 3) of the highest peak
    refined by a 3-point fit per axis, the raw peak height, and the ratio of the primary
    peak to the highest other face-connected local maximum.
refine_peaks
    For the same planes: the displacement (n, 3) of the highest peak refined per axis on the
    correlation divided by the windows' overlap fraction (the loss of particle pairs across
    the window border, which pulls a fitted peak towards zero), with a least-squares Gaussian
    on five samples along an axis where the peak is broad, on seven where it is wide (see
    :func:`_refine_axis_numba`).
deform_trilinear
    Sample a volume at ``x + factor * d(x)`` by trilinear interpolation (zero outside).
deform_cubic
    Sample a cubic B-spline, given by its coefficients on a zero-padded grid, at
    ``x + factor * d(x)``.
neighbour_median
    Median of the usable 3x3x3 neighbours (centre excluded) of every vector of a field, and
    the median of those neighbours' absolute residuals: the two ingredients of the
    normalised median test.
peak_statistics
    For window pairs at given start voxels and their integer correlation peak: the peak
    value and its two neighbours along each axis, built from the products of the two
    windows' intensities, and the variance of the asymmetry of those neighbours (the
    correlation statistics of Wieneke 2015, in 3-D, with the covariance of neighbouring
    voxels' contributions).

Each family lives in its own module (:mod:`.spectra`, :mod:`.peaks`, :mod:`.deform`,
:mod:`.median`, :mod:`.statistics`); a kernel ``name`` has its twin ``name_numpy`` next to it.
"""

from types import SimpleNamespace

from plenopiv.piv._kernels.deform import (
    deform_cubic,
    deform_cubic_numpy,
    deform_trilinear,
    deform_trilinear_numpy,
)
from plenopiv.piv._kernels.median import neighbour_median, neighbour_median_numpy
from plenopiv.piv._kernels.peaks import (
    find_peaks,
    find_peaks_numpy,
    refine_peaks,
    refine_peaks_numpy,
)
from plenopiv.piv._kernels.spectra import (
    cross_spectrum,
    cross_spectrum_numpy,
    extract_windows,
    extract_windows_numpy,
)
from plenopiv.piv._kernels.statistics import peak_statistics, peak_statistics_numpy

ENGINES = {
    "numba": SimpleNamespace(
        extract_windows=extract_windows,
        cross_spectrum=cross_spectrum,
        find_peaks=find_peaks,
        refine_peaks=refine_peaks,
        deform_trilinear=deform_trilinear,
        deform_cubic=deform_cubic,
        neighbour_median=neighbour_median,
        peak_statistics=peak_statistics,
    ),
    "numpy": SimpleNamespace(
        extract_windows=extract_windows_numpy,
        cross_spectrum=cross_spectrum_numpy,
        find_peaks=find_peaks_numpy,
        refine_peaks=refine_peaks_numpy,
        deform_trilinear=deform_trilinear_numpy,
        deform_cubic=deform_cubic_numpy,
        neighbour_median=neighbour_median_numpy,
        peak_statistics=peak_statistics_numpy,
    ),
}
"""The kernel sets by name; both hold the same eight functions with the same signatures."""
