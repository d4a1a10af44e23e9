"""Numerical kernels of :mod:`plenopiv.piv`, each a numba function with its plain-NumPy twin.

Every kernel takes arrays and scalars only and returns new arrays (``cross_spectrum`` writes
into the ``out`` array its caller passes). A kernel ``name`` has its twin ``name_numpy`` next
to it, with one signature and one meaning; the tests run both, and
:func:`plenopiv.piv.correlate_volumes` chooses one by its ``engine`` (``"numba"``, the default,
or ``"numpy"``). Positions, shifts and displacements are in voxels, ordered ``(z, y, x)``.
The families, each in its module: :mod:`.spectra` (``extract_windows``, ``cross_spectrum``),
:mod:`.peaks` (``find_peaks``, ``refine_peaks``), :mod:`.deform` (``deform_trilinear``,
``deform_cubic``), :mod:`.median` (``neighbour_median``) and :mod:`.statistics`
(``peak_statistics``).
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
