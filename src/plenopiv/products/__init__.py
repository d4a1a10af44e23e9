"""What plenopiv reads and writes: images, HDF5 products and their schemas, JSON.

:mod:`~plenopiv.products.files` (output paths, atomic writes), :mod:`~plenopiv.products.hdf5`
(writing and opening HDF5 products), :mod:`~plenopiv.products.provenance` (schema versions,
what made each product), :mod:`~plenopiv.products.images` (reading, checking and writing
images), :mod:`~plenopiv.products.jsonio` (JSON text), and the product schemas:
:mod:`~plenopiv.products.volume` (the volume product) and :mod:`~plenopiv.products.vectors`
(the vectors product). Every write is atomic. Import the submodules; this package imports
nothing, so that a light command does not load h5py.
"""
