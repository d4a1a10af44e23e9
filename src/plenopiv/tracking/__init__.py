"""Particle tracking from the light field: ray-bundle positions and PIV-guided matching.

:mod:`plenopiv.tracking.bundle`
    each particle's 3-D position as the point nearest the bundle of its rays (the pixels whose
    beams pass it, weighted by their intensity), with a covariance from the fit;
:mod:`plenopiv.tracking.matching`
    particles of exposure A matched to those of B with the correlation field as predictor
    (hybrid PIV-PTV, Keane, Adrian & Zhang 1995);
:mod:`plenopiv.tracking.products`
    the tracks product (HDF5, ``.vtp``) and the tracks binned onto the PIV grid (the vectors
    product they are binned on is read by :func:`plenopiv.products.vectors.load_vectors`);
:mod:`plenopiv.tracking.pair`
    one pair end to end (orchestration for ``plenopiv track`` and ``plenopiv run``).
"""
