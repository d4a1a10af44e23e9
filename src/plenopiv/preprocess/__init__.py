"""Preprocessing: from the recorded image to the particle light the reconstruction assumes.

One stage between the raw image and the light field (docs/design.md §2): dark subtraction
(:mod:`~plenopiv.preprocess.dark`), background removal (:mod:`~plenopiv.preprocess.background`),
hot and dead pixels found and repaired inside their micro-images
(:mod:`~plenopiv.preprocess.pixels`, :mod:`~plenopiv.preprocess.microimages`), the flat field
of a white image (:mod:`~plenopiv.preprocess.flat`), and the two exposures of a pair on one
intensity scale (:mod:`~plenopiv.preprocess.intensity`); :mod:`~plenopiv.preprocess.stage`
applies them in order, :mod:`~plenopiv.preprocess.condition` says what an image as it comes
needs. The ``[preprocess]`` table is :class:`PreprocessSettings`. See
docs/methods.md#preprocessing.
"""

from plenopiv.preprocess.background import batch_background, subtract_background
from plenopiv.preprocess.condition import ImageCondition, advice, image_condition
from plenopiv.preprocess.dark import MasterDark, master_dark, subtract_dark
from plenopiv.preprocess.flat import FlatField, apply_flat, flat_field
from plenopiv.preprocess.intensity import exposure_level, normalise_pair
from plenopiv.preprocess.microimages import (
    MicroImages,
    gap_level,
    micro_images,
    micro_images_from_centres,
)
from plenopiv.preprocess.pixels import (
    dark_defects,
    isolated_pixels,
    neighbour_stats,
    repair_pixels,
    white_defects,
)
from plenopiv.preprocess.settings import PreprocessSettings
from plenopiv.preprocess.stage import Frames, Prepared, prepare_frames, prepare_image, prepare_pair

__all__ = [
    "FlatField",
    "Frames",
    "ImageCondition",
    "MasterDark",
    "MicroImages",
    "PreprocessSettings",
    "Prepared",
    "advice",
    "apply_flat",
    "batch_background",
    "dark_defects",
    "exposure_level",
    "flat_field",
    "gap_level",
    "image_condition",
    "isolated_pixels",
    "master_dark",
    "micro_images",
    "micro_images_from_centres",
    "neighbour_stats",
    "normalise_pair",
    "prepare_frames",
    "prepare_image",
    "prepare_pair",
    "repair_pixels",
    "subtract_background",
    "subtract_dark",
    "white_defects",
]
