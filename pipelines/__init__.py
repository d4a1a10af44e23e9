"""End-to-end pipelines and the validation studies of plenopiv (not installed with the package).

The scripts ``validate_*.py`` run the studies of :mod:`pipelines.studies` from a clone of the
repository: ``python pipelines/validate_depth.py --out docs/validation``.
"""
