"""Ray-traced plenoptic image simulator (the project's ALFA): calibration and particle images."""
