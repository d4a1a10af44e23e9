"""Particles: peaks of a reconstructed volume and positions from the rays that saw them.

:mod:`~plenopiv.particles.peaks` finds local maxima above the volume's noise
(:mod:`~plenopiv.particles.threshold`) and their sub-voxel positions;
:mod:`~plenopiv.particles.bundle` and :mod:`~plenopiv.particles.forward` locate a particle from
the bundle of its rays across lenslets. See docs/methods.md#particles.
"""
