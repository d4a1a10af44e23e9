"""The camera: its model, optics, resolution cell, volume grid and depth corrections.

The frozen model (sensor, microlens array, main lens, interfaces), its geometric optics, the
resolution cell, the volume grid and the depth corrections of the refractive interfaces. See
docs/methods.md#camera-and-optics for the physics.
"""
