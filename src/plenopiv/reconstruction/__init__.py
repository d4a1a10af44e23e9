"""Reconstruction of a particle volume from one plenoptic image.

The projectors (explicit weights, matrix-free lattice), their choice and on-disk cache
(:mod:`.weights`), the line-of-sight mask (:mod:`.sightline`) and MART/SMART (:mod:`.mart`).
"""
