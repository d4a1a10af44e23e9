"""Particles: peaks of a reconstructed volume and positions from the rays that saw them.

:mod:`~plenopiv.particles.peaks` finds local maxima with a sub-voxel centroid;
:mod:`~plenopiv.particles.bundle` and :mod:`~plenopiv.particles.forward` locate a particle from
the bundle of its rays across lenslets. See docs/methods.md#particles.
"""
