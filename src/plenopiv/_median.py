"""The median of a few values inside a numba kernel, without allocating.

Shared by the PIV's normalised median test and the preprocessing's neighbour statistics.
"""

from __future__ import annotations

import numba


@numba.njit(cache=True)
def small_median(a, n):
    """Median of ``a[:n]`` (n >= 1), sorting ``a[:n]`` in place.

    An insertion sort of a few dozen values at most: no array per call, and it compiles in
    a fraction of the time of ``np.median``.
    """
    for i in range(1, n):
        v = a[i]
        j = i - 1
        while j >= 0 and a[j] > v:
            a[j + 1] = a[j]
            j -= 1
        a[j + 1] = v
    h = n // 2
    return a[h] if n % 2 else 0.5 * (a[h - 1] + a[h])
