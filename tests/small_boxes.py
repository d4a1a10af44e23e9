"""Cameras and boxes the reconstruction's choice and budget tests share."""

from __future__ import annotations

import dataclasses

from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import load_camera
from plenopiv.camera.resolution import footprint


def camera(name):
    """A preset, or ``NAME+rotated``: its lenslet array rotated by 2 mrad."""
    base, _, variant = name.partition("+")
    cam = load_camera(base)
    if variant == "rotated":
        mla = dataclasses.replace(cam.microlens_array, rotation=2e-3)
        cam = cam.replace(microlens_array=mla)
    return cam


def box(cam, voxel_footprints, half=4):
    """A box of ``2 half`` footprints a side, 1.5 mm deep, voxels of ``voxel_footprints``."""
    b = footprint(cam)
    v = voxel_footprints * b
    return VolumeGrid.from_bounds((-half * b, half * b), (-half * b, half * b),
                                  (-0.75e-3, 0.75e-3), voxel=(v, v, 0.25e-3))
