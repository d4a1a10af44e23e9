"""The camera: the frozen model (sensor, microlens array, main lens, interfaces), its optics,
its resolution cell, the volume grid and the depth corrections of its refractive interfaces.

See docs/methods.md for the physics.
"""
