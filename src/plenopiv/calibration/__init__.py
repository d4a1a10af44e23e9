"""Calibration of a plenoptic camera: lenslet and focal-spot centres, image distance."""
