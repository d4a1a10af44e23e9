"""The camera: its frozen model, optics, resolution cell, volume grid and depth corrections.

See docs/methods.md for the physics.
"""
