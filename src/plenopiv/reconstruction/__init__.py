"""Reconstruction of a particle volume from one plenoptic image.

The projectors (explicit weights, matrix-free lattice and per-lenslet), their choice and
on-disk cache (:mod:`.weights`, :mod:`.select`), the line-of-sight mask (:mod:`.sightline`) and
MART/SMART (:mod:`.mart`). See docs/methods.md#reconstruction.
"""
