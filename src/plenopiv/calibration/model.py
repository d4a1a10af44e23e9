"""The calibration product: what the reconstruction needs to know about a camera.

A :class:`Calibration` holds, for every lenslet, its centre, its focal spot and its lattice
index, plus the effective image distance S_i,eff and how it was obtained. S_i,eff is kept in
one place, the main lens of the calibration's camera (:attr:`Calibration.camera`). It is saved
as the HDF5 product of docs/design.md §7 (``/lenslets/centre_px``, ``/lenslets/focal_spot_px``,
``/lenslets/grid_index``; attributes ``image_distance_m``, ``method``, ``offset_m``,
``rotation_rad``, ``rms_residual_px``, ``camera`` and ``camera_summary``); using it with
another camera is an error naming both
(:func:`plenopiv.workflow.experiment.experiment_calibration`). A product without the
``camera`` attribute is read with the camera of its ``config`` attribute.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plenopiv.camera import optics
from plenopiv.camera.model import CameraModel, camera_from_dict
from plenopiv.conventions import sensor_to_pixel
from plenopiv.errors import CalibrationError
from plenopiv.products.hdf5 import open_product, write_h5
from plenopiv.products.jsonio import dumps
from plenopiv.products.provenance import json_hash, make_provenance


@dataclass(frozen=True)
class Calibration:
    """A calibrated plenoptic camera.

    Attributes
    ----------
    camera : CameraModel
        The camera, its main lens's ``image_distance`` the calibrated effective image distance
        S_i,eff, m: the one place the calibration keeps it.
    centre_px : (N, 2) float
        Lenslet centres (row, col), pixels: where collimated light focuses.
    focal_spot_px : (N, 2) float
        Micro-image centres (row, col), pixels: where the chief ray from the pupil centre
        through the lenslet centre lands (u = v = 0).
    grid_index : (N, 2) int
        Lattice index (row, col) of each lenslet.
    method : str
        "focal-point", "magnification", "both" or "model" (from the camera description).
    offset : tuple of float
        Fitted lenslet-array offset (x, y), m.
    rotation : float
        Fitted lenslet-array rotation, rad.
    rms_residual_px : float
        Rms residual of the focal-point fit, px.
    extra : dict
        Further figures of the calibration (JSON-ready).
    """

    camera: CameraModel
    centre_px: np.ndarray
    focal_spot_px: np.ndarray
    grid_index: np.ndarray
    method: str
    offset: tuple[float, float] = (0.0, 0.0)
    rotation: float = 0.0
    rms_residual_px: float = 0.0
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        n = len(self.centre_px)
        for name in ("centre_px", "focal_spot_px", "grid_index"):
            a = np.asarray(getattr(self, name))
            if a.shape != (n, 2):
                raise CalibrationError(f"calibration {name} has shape {a.shape}: expected "
                                       f"({n}, 2)")
        if self.camera.main_lens.image_distance is None:
            raise CalibrationError("the calibration's camera has no image distance: expected "
                                   "the calibrated S_i in its main lens")
        if not self.image_distance > self.camera.main_lens.focal_length:
            raise CalibrationError(f"calibrated S_i = {self.image_distance * 1e3:.4g} mm: "
                                   "expected more than the main-lens focal length")

    @property
    def n_lenslets(self) -> int:
        """Number of calibrated lenslets."""
        return len(self.centre_px)

    @property
    def image_distance(self) -> float:
        """Calibrated effective image distance S_i,eff, m (held by :attr:`camera`)."""
        return self.camera.main_lens.image_distance

    @property
    def point_spread_sigma_px(self) -> float | None:
        """Standard deviation of the sensor's Gaussian point spread, px.

        Measured on the focal-point image (``extra["point_spread_sigma_px"]``,
        :func:`plenopiv.calibration.psf.point_spread_sigma`); None when not measured.
        """
        value = self.extra.get("point_spread_sigma_px")
        return None if value is None else float(value)

    @property
    def effective_camera(self) -> CameraModel:
        """The camera with the calibrated image distance: :attr:`camera` itself."""
        return self.camera

    def with_camera(self, camera: CameraModel) -> Calibration:
        """The same calibration for another description of its camera, with the calibrated S_i.

        Parameters
        ----------
        camera : CameraModel
            E.g. the experiment's camera (its interfaces and back-side model); its own
            ``image_distance`` is replaced by :attr:`image_distance`.
        """
        return dataclasses.replace(self, camera=camera.with_image_distance(self.image_distance))

    @classmethod
    def from_camera(cls, camera: CameraModel) -> Calibration:
        """The exact calibration of a modelled camera (chief rays from its exit pupil).

        Used for synthetic studies where the truth is known; real data go through
        :mod:`plenopiv.calibration.calibrate`.
        """
        mla = camera.microlens_array
        centres = mla.centres()
        spots = optics.focal_spot_exact(centres, camera.image_distance, mla.sensor_distance,
                                        back_side=mla.back_side,
                                        thickness=camera.plate_thickness,
                                        refractive_index=camera.plate_index,
                                        pupil_offset=camera.main_lens.exit_pupil_offset)
        shape, pp = camera.sensor.shape, camera.sensor.pixel_pitch
        return cls(camera=camera, centre_px=sensor_to_pixel(centres, shape, pp),
                   focal_spot_px=sensor_to_pixel(spots, shape, pp),
                   grid_index=mla.grid_index(), method="model", offset=mla.offset,
                   rotation=mla.rotation)

    # ---- HDF5 product ------------------------------------------------------------------------
    def save(self, path: str | Path, *, config: dict | None = None,
             provenance: dict | None = None) -> Path:
        """Write the calibration product (HDF5, atomic).

        ``provenance``: what made it (:func:`~plenopiv.products.provenance.make_provenance`);
        without it, the camera's hash alone.
        """
        cfg = {"camera": self.camera.to_dict(), **(config or {})}
        cam = self.camera
        mla = cam.microlens_array
        attrs = {"camera": cam.to_json(),
                 "camera_summary": (
                     f"{cam.name}: main lens f = "
                     f"{cam.main_lens.focal_length * 1e3:g} mm, S_i = "
                     f"{self.image_distance * 1e3:.6g} mm, {mla.rows} x {mla.cols} {mla.grid} "
                     f"lenslets of {mla.pitch * 1e6:g} um, sensor {cam.sensor.rows} x "
                     f"{cam.sensor.cols} px of {cam.sensor.pixel_pitch * 1e6:g} um"),
                 "image_distance_m": self.image_distance, "method": self.method,
                 "offset_m": np.asarray(self.offset, float), "rotation_rad": self.rotation,
                 "rms_residual_px": self.rms_residual_px, "n_lenslets": self.n_lenslets,
                 "extra": dumps(self.extra, default=float)}
        return write_h5(path, {"/lenslets/centre_px": np.asarray(self.centre_px, float),
                               "/lenslets/focal_spot_px": np.asarray(self.focal_spot_px, float),
                               "/lenslets/grid_index": np.asarray(self.grid_index, np.int32)},
                        attrs=attrs, units={"/lenslets/centre_px": "px",
                                            "/lenslets/focal_spot_px": "px",
                                            # lattice (row, column) index: a count
                                            "/lenslets/grid_index": "1"},
                        config=cfg, kind="calibration",
                        provenance=provenance or make_provenance(
                            "calibration", settings={"camera": json_hash(cam.to_dict())}))

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        """Read a calibration product written by :meth:`save`.

        Every array and number is checked finite (a damaged product is refused naming the
        file and the dataset); S_i must be a length > 0.
        """
        with open_product(path, "calibration", CalibrationError) as fh:
            a = fh.attrs
            if "camera" in a:
                camera = camera_from_dict(json.loads(a["camera"]), source=f"{path}:camera")
            else:             # written before the camera attribute: the config's camera
                camera = camera_from_dict(json.loads(a["config"])["camera"],
                                          source=f"{path}:config")
            # the product's S_i is its image_distance_m attribute (the camera's copy went
            # through mm, and older files' config may not hold it)
            camera = camera.with_image_distance(_positive(fh.number("image_distance_m"),
                                                          "image_distance_m", path))
            return cls(camera=camera,
                       centre_px=fh.array("/lenslets/centre_px").astype(float),
                       focal_spot_px=fh.array("/lenslets/focal_spot_px").astype(float),
                       grid_index=fh.array("/lenslets/grid_index").astype(int),
                       method=str(a["method"]),
                       offset=tuple(float(v) for v in fh.number("offset_m")),
                       rotation=fh.number("rotation_rad"),
                       rms_residual_px=fh.number("rms_residual_px", allow_nan=True),
                       extra=json.loads(a.get("extra", "{}")))


def _positive(value: float, name: str, path) -> float:
    """A calibrated length of the product, refused unless > 0."""
    if not value > 0:
        raise CalibrationError(f"calibration {str(path)!r}: {name} = {value!r}: expected a "
                               "finite length > 0; the product is damaged, calibrate again")
    return value
