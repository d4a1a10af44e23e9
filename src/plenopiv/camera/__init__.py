"""The camera: its frozen model, optics, resolution cell, volume grid and depth corrections.

The model holds the sensor, microlens array, main lens and interfaces; the depth corrections
are those of its refractive interfaces.

See docs/methods.md for the physics.
"""
