"""Particle tracking: particles of exposure A matched to those of B.

The correlation field is the predictor (hybrid PIV-PTV, Keane, Adrian & Zhang 1995).

The positions come from :mod:`plenopiv.particles.peaks`; a pair end to end is
:mod:`plenopiv.workflow.tracking`; the tracks product is :mod:`plenopiv.products.tracks`.
"""
