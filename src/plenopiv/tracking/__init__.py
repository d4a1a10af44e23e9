"""Particle tracking: particles of exposure A matched to those of B, the PIV field predicting.

The positions come from :mod:`plenopiv.particles`; a pair end to end is
:mod:`plenopiv.workflow.tracking`; the tracks product is :mod:`plenopiv.products.tracks`.
Matching after Keane, Adrian & Zhang (1995).
"""
