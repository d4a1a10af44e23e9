"""Numba kernels of the reconstruction: one module per family, each with its NumPy twin."""
