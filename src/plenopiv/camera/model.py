"""The plenoptic 1.0 camera model: sensor, microlens array, main lens, refractive interfaces.

Frozen parameter objects in SI units (metres, radians), checked when they are made:
:class:`Sensor`, :class:`Substrate`, :class:`MicrolensArray`, :class:`MainLens`,
:class:`ExternalInterface` and :class:`CameraModel`. Camera files (TOML, ``_mm``/``_um`` keys,
docs/design.md §7) are converted once, at the boundary, by :func:`camera_from_dict` /
:func:`load_camera`, which raise :class:`~plenopiv.errors.ConfigError` naming the key, the
value found and what was expected. ``image_distance`` is the effective (air-equivalent)
S_i,eff = l3 + t/n (thesis Eq. 4.4).

See docs/methods.md#camera-geometry for the geometry along the optical axis.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, ValidationError

from plenopiv.errors import ConfigError
from plenopiv.products.jsonio import dumps
from plenopiv.settings import StrictModel, format_validation_error, validate_table

GRIDS = ("square", "hexagonal")
BACK_SIDES = ("physical", "thesis")

PRESET_DIR = Path(__file__).resolve().parents[1] / "presets"


# --------------------------------------------------------------------------------------------
# Frozen SI parameter objects
# --------------------------------------------------------------------------------------------


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise ConfigError(message)


@dataclass(frozen=True)
class Sensor:
    """Image sensor.

    Attributes
    ----------
    rows, cols : int
        Pixel counts (image shape is ``(rows, cols)``).
    pixel_pitch : float
        Pixel pitch, metres.
    """

    rows: int
    cols: int
    pixel_pitch: float

    def __post_init__(self):
        _require(self.rows >= 2 and self.cols >= 2,
                 f"[sensor] rows = {self.rows}, cols = {self.cols}: expected at least 2 × 2 pixels")
        _require(self.pixel_pitch > 0,
                 f"[sensor] pixel_pitch_um = {self.pixel_pitch * 1e6:g}: expected > 0")

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape ``(rows, cols)``."""
        return (self.rows, self.cols)

    @property
    def width(self) -> float:
        """Sensor width along x (cols), metres."""
        return self.cols * self.pixel_pitch

    @property
    def height(self) -> float:
        """Sensor height along y (rows), metres."""
        return self.rows * self.pixel_pitch


@dataclass(frozen=True)
class Substrate:
    """Glass plate carrying the lenslets (between main lens and lenslets).

    Attributes
    ----------
    thickness : float
        Plate thickness t, metres.
    refractive_index : float
        Index n of the glass.
    """

    thickness: float
    refractive_index: float

    def __post_init__(self):
        _require(self.thickness > 0,
                 f"[microlens_array.substrate] thickness_mm = {self.thickness * 1e3:g}: "
                 "expected > 0 (leave the section out for no plate)")
        _require(self.refractive_index >= 1.0,
                 f"[microlens_array.substrate] refractive_index = {self.refractive_index:g}: "
                 "expected >= 1")

    @property
    def air_equivalent_thickness(self) -> float:
        """t/n, metres: the air path that the plate is equivalent to (thesis Eq. 4.4)."""
        return self.thickness / self.refractive_index


@dataclass(frozen=True)
class MicrolensArray:
    """Microlens array (MLA).

    Attributes
    ----------
    rows, cols : int
        Lenslet counts.
    pitch : float
        Lenslet pitch, metres (centre-to-centre along a row; for a hexagonal grid the row
        spacing is ``pitch * sqrt(3)/2`` and odd rows are shifted by ``pitch/2`` along x).
    focal_length : float
        Lenslet focal length f_l, metres.
    sensor_distance : float
        Distance f̄ from the lenslet plane to the sensor, metres.
    grid : {"square", "hexagonal"}
    offset : tuple of float
        Misplacement ``(s_o, t_o)`` of the array, metres (thesis Eqs. 3.13-3.14).
    rotation : float
        Misplacement rotation γ, radians, counter-clockwise in (x, y).
    back_side : {"physical", "thesis"}
        "physical": the lenslets are on the sensor side of the substrate and a ray regains
        its air angle when it leaves the glass (focal spots follow Eq. 3.11 with S_i,eff).
        "thesis": the ray keeps its in-glass angle down to the sensor (Appendix B, Eq. 4.8).
    substrate : Substrate or None
    """

    rows: int
    cols: int
    pitch: float
    focal_length: float
    sensor_distance: float
    grid: Literal["square", "hexagonal"] = "square"
    offset: tuple[float, float] = (0.0, 0.0)
    rotation: float = 0.0
    back_side: Literal["physical", "thesis"] = "physical"
    substrate: Substrate | None = None

    def __post_init__(self):
        _require(self.rows >= 1 and self.cols >= 1,
                 f"[microlens_array] rows = {self.rows}, cols = {self.cols}: expected >= 1")
        _require(self.pitch > 0, f"[microlens_array] pitch_um = {self.pitch * 1e6:g}: expected > 0")
        _require(self.focal_length > 0,
                 f"[microlens_array] focal_length_um = {self.focal_length * 1e6:g}: expected > 0")
        _require(self.sensor_distance > 0,
                 f"[microlens_array] sensor_distance_um = {self.sensor_distance * 1e6:g}: "
                 "expected > 0")
        _require(self.grid in GRIDS,
                 f"[microlens_array] grid = {self.grid!r}: expected one of {GRIDS}")
        _require(self.back_side in BACK_SIDES,
                 f"[microlens_array] back_side = {self.back_side!r}: expected one of {BACK_SIDES}")
        _require(len(self.offset) == 2 and all(math.isfinite(v) for v in self.offset),
                 f"[microlens_array] offset_um = {self.offset}: expected two finite numbers")
        _require(abs(self.rotation) < math.pi / 8,
                 f"[microlens_array] rotation_rad = {self.rotation:g}: expected |γ| < π/8 "
                 "(a small misplacement)")
        object.__setattr__(self, "offset", (float(self.offset[0]), float(self.offset[1])))

    @property
    def row_spacing(self) -> float:
        """Distance between lenslet rows, metres."""
        return self.pitch * (math.sqrt(3.0) / 2.0 if self.grid == "hexagonal" else 1.0)

    @property
    def count(self) -> int:
        """Number of lenslets."""
        return self.rows * self.cols

    @property
    def extent(self) -> tuple[float, float]:
        """Outer size ``(width, height)`` of the array, metres."""
        if self.grid == "hexagonal":
            width = (self.cols + (0.5 if self.rows > 1 else 0.0)) * self.pitch
            height = (self.rows - 1) * self.row_spacing + self.pitch
        else:
            width, height = self.cols * self.pitch, self.rows * self.pitch
        return width, height

    @property
    def hex_shift_mean(self) -> float:
        """Mean x shift (in pitches) of the odd rows of a hexagonal grid, removed to centre it."""
        if self.grid != "hexagonal":
            return 0.0
        return 0.5 * (self.rows // 2) / self.rows

    def grid_index(self) -> np.ndarray:
        """Grid index ``(row, col)`` of every lenslet, shape (N, 2), row-major order."""
        r, c = np.meshgrid(np.arange(self.rows), np.arange(self.cols), indexing="ij")
        return np.stack([r.ravel(), c.ravel()], axis=1)

    def nominal_centres(self) -> np.ndarray:
        """Lenslet centres ``(s, t)`` of a perfectly placed array, metres, shape (N, 2).

        The array is centred on the optical axis: ``s = (col - (cols-1)/2) * pitch`` and
        ``t = (row - (rows-1)/2) * row_spacing`` (plus ``pitch/2`` on odd hexagonal rows,
        less the mean of that shift).
        """
        idx = self.grid_index()
        row, col = idx[:, 0].astype(float), idx[:, 1].astype(float)
        shift = 0.5 * (idx[:, 0] % 2) - self.hex_shift_mean if self.grid == "hexagonal" else 0.0
        s = (col - (self.cols - 1) / 2.0 + shift) * self.pitch
        t = (row - (self.rows - 1) / 2.0) * self.row_spacing
        return np.stack([s, t], axis=1)

    def centres(self) -> np.ndarray:
        """Lenslet centres ``(s, t)`` after the misplacement, metres, shape (N, 2).

        Notes
        -----
        Thesis Eqs. 3.13-3.14::

            s_new = (s + s_o) cos γ - (t + t_o) sin γ
            t_new = (s + s_o) sin γ + (t + t_o) cos γ
        """
        return apply_misplacement(self.nominal_centres(), self.offset, self.rotation)


def apply_misplacement(centres, offset, rotation):
    """Apply the MLA offset and rotation of thesis Eqs. 3.13-3.14.

    Parameters
    ----------
    centres : array_like, shape (N, 2)
        Lenslet centres ``(s, t)``, metres.
    offset : array_like, shape (2,)
        ``(s_o, t_o)``, metres.
    rotation : float
        γ, radians.
    """
    d = np.asarray(centres, dtype=float) + np.asarray(offset, dtype=float)
    c, s = math.cos(rotation), math.sin(rotation)
    return np.stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]], axis=1)


@dataclass(frozen=True)
class MainLens:
    """Main (thin) lens.

    Attributes
    ----------
    focal_length : float
        f_m, metres.
    f_number : float
        N; the aperture (entrance and exit pupil) diameter is f_m/N.
    image_distance : float or None
        Effective (air-equivalent) image distance S_i,eff, metres; needed to simulate.
    exit_pupil_offset : float
        Exit pupil minus principal plane, metres, + towards the sensor. Chief rays in image
        space leave from the exit pupil centre (0, 0, offset).
    image_distance_origin : str or None
        Where ``image_distance`` came from, so that messages name what the user gave (see
        :meth:`image_distance_text`): None, the camera file's ``[main_lens]
        image_distance_mm``; a command-line option (``"--image-distance-mm"``); or the
        calibration that measured it (e.g. ``"from 'cal.h5'"``). Not compared.
    """

    focal_length: float
    f_number: float
    image_distance: float | None = None
    exit_pupil_offset: float = 0.0
    image_distance_origin: str | None = field(default=None, compare=False, repr=False)

    def __post_init__(self):
        _require(self.focal_length > 0,
                 f"[main_lens] focal_length_mm = {self.focal_length * 1e3:g}: expected > 0")
        _require(self.f_number > 0, f"[main_lens] f_number = {self.f_number:g}: expected > 0")
        if self.image_distance is not None:
            _require(self.image_distance > self.focal_length,
                     f"{self.image_distance_text()}: expected > [main_lens] "
                     f"focal_length_mm = {self.focal_length * 1e3:g} (a real image)")
            _require(self.exit_pupil_offset < self.image_distance,
                     f"[main_lens] exit_pupil_offset_mm = {self.exit_pupil_offset * 1e3:g}: "
                     f"expected less than {self.image_distance_text()}")

    def image_distance_text(self) -> str:
        """How a message names S_i: as the user gave it, or as calibrated (never a key unwritten).

        ``[main_lens] image_distance_mm = 200`` (the camera file), ``--image-distance-mm
        200`` (an option), or ``the calibrated image distance S_i = 76.8 mm (from 'cal.h5')``.
        """
        mm = self.image_distance * 1e3
        origin = self.image_distance_origin
        if origin is None:
            return f"[main_lens] image_distance_mm = {mm:g}"
        if origin.startswith("--"):
            return f"{origin} {mm:g}"
        return f"the calibrated image distance S_i = {mm:.4g} mm ({origin})"

    @property
    def aperture_diameter(self) -> float:
        """Pupil diameter f_m/N, metres."""
        return self.focal_length / self.f_number


@dataclass(frozen=True)
class ExternalInterface:
    """A flat window between the particles' medium and the camera.

    Attributes
    ----------
    refractive_index : float
        n1, the medium holding the particles (1.33 for water).
    outside_index : float
        n2, the medium on the camera side (1.0 for air).
    medium_depth : float
        l1, metres: path in the medium from the interface to the nominal focal plane.
    """

    refractive_index: float
    outside_index: float = 1.0
    medium_depth: float = 0.0

    def __post_init__(self):
        _require(self.refractive_index >= 1.0,
                 f"[external_interface] refractive_index = {self.refractive_index:g}: "
                 "expected >= 1")
        _require(self.outside_index >= 1.0,
                 f"[external_interface] outside_index = {self.outside_index:g}: expected >= 1")
        _require(self.medium_depth >= 0,
                 f"[external_interface] medium_depth_mm = {self.medium_depth * 1e3:g}: "
                 "expected >= 0")

    @property
    def depth_ratio(self) -> float:
        """n2/n1: effective depth per physical depth in the medium (thesis Eq. 4.7)."""
        return self.outside_index / self.refractive_index


@dataclass(frozen=True)
class CameraModel:
    """A whole plenoptic camera; derived distances are properties, never stored twice."""

    sensor: Sensor
    microlens_array: MicrolensArray
    main_lens: MainLens
    external_interface: ExternalInterface | None = None
    name: str = "plenoptic camera"
    source: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self):
        mla, sen = self.microlens_array, self.sensor
        pitch_px = mla.pitch / sen.pixel_pitch
        _require(pitch_px >= 2.0,
                 f"[microlens_array] pitch_um = {mla.pitch * 1e6:g} is {pitch_px:.3g} pixels of "
                 f"[sensor] pixel_pitch_um = {sen.pixel_pitch * 1e6:g}: expected at least 2 pixels "
                 "per lenslet")
        width, height = mla.extent
        _require(width <= sen.width * (1 + 1e-9),
                 f"[microlens_array] cols = {mla.cols} lenslets of pitch_um = "
                 f"{mla.pitch * 1e6:g} span {width * 1e3:.4g} mm, wider than the sensor "
                 f"([sensor] cols = {sen.cols} of pixel_pitch_um = {sen.pixel_pitch * 1e6:g}, "
                 f"{sen.width * 1e3:.4g} mm): expected the array to fit on the sensor")
        _require(height <= sen.height * (1 + 1e-9),
                 f"[microlens_array] rows = {mla.rows} lenslets of pitch_um = "
                 f"{mla.pitch * 1e6:g} span {height * 1e3:.4g} mm, taller than the sensor "
                 f"([sensor] rows = {sen.rows} of pixel_pitch_um = {sen.pixel_pitch * 1e6:g}, "
                 f"{sen.height * 1e3:.4g} mm): expected the array to fit on the sensor")
        if self.external_interface is not None and self.main_lens.image_distance is not None:
            _require(self.interface_distance > 0,
                     f"[external_interface] medium_depth_mm = "
                     f"{self.external_interface.medium_depth * 1e3:g}: the interface would lie "
                     f"behind the main lens (S_o,eff = {self.object_distance * 1e3:.4g} mm, "
                     f"from {self.main_lens.image_distance_text()}); expected (n2/n1)·l1 < "
                     "S_o,eff")

    # ---- derived distances (metres) --------------------------------------------------------
    @property
    def pitch_px(self) -> float:
        """Lenslet pitch in sensor pixels."""
        return self.microlens_array.pitch / self.sensor.pixel_pitch

    @property
    def image_distance(self) -> float:
        """Effective image distance S_i,eff, metres (raises if the config does not give it)."""
        si = self.main_lens.image_distance
        if si is None:
            raise ConfigError("[main_lens] image_distance_mm is not set: expected the effective "
                              "image distance S_i (mm) to simulate or reconstruct")
        return si

    @property
    def object_distance(self) -> float:
        """Effective object distance S_o,eff = 1/(1/f_m - 1/S_i,eff), metres (Eq. 3.1)."""
        f, si = self.main_lens.focal_length, self.image_distance
        return 1.0 / (1.0 / f - 1.0 / si)

    @property
    def magnification(self) -> float:
        """M = -S_i,eff/S_o,eff (negative: the image is inverted)."""
        return -self.image_distance / self.object_distance

    @property
    def plate_thickness(self) -> float:
        """Substrate thickness t, metres (0 without a substrate)."""
        sub = self.microlens_array.substrate
        return 0.0 if sub is None else sub.thickness

    @property
    def plate_index(self) -> float:
        """Substrate index n (1 without a substrate)."""
        sub = self.microlens_array.substrate
        return 1.0 if sub is None else sub.refractive_index

    @property
    def mla_z(self) -> float:
        """Physical z of the lenslet plane: S_i,eff + t(1 - 1/n), metres."""
        return self.image_distance + self.plate_thickness * (1.0 - 1.0 / self.plate_index)

    @property
    def l3(self) -> float:
        """Air path from the main lens to the substrate (to the lenslets without one), metres."""
        return self.mla_z - self.plate_thickness

    @property
    def sensor_z(self) -> float:
        """Physical z of the sensor plane, metres."""
        return self.mla_z + self.microlens_array.sensor_distance

    @property
    def interface_distance(self) -> float:
        """l2: air path from the main lens to the external interface, metres (Eq. 4.3)."""
        ext = self.external_interface
        if ext is None:
            return self.object_distance
        return self.object_distance - ext.depth_ratio * ext.medium_depth

    @property
    def focal_plane_z(self) -> float:
        """Physical z (< 0) of the nominal focal plane, metres.

        Without an external interface this is -S_o,eff; with one it is -(l2 + l1): the
        interface sits at z = -l2 and the medium of index n1 fills everything beyond it.
        """
        ext = self.external_interface
        if ext is None:
            return -self.object_distance
        return -(self.interface_distance + ext.medium_depth)

    def volume_to_camera(self, points) -> np.ndarray:
        """Volume points (X, Y, Z) (N, 3), metres, to camera coordinates (x, y, z), z < 0.

        Z is the physical depth from the nominal focal plane, + away from the camera
        (in the medium when there is an external interface).
        """
        p = np.array(points, dtype=float, ndmin=2)
        p[:, 2] = self.focal_plane_z - p[:, 2]
        return p

    # ---- conversions -----------------------------------------------------------------------
    def replace(self, **sections) -> CameraModel:
        """Return a copy with whole sections replaced (``sensor=..., main_lens=...``)."""
        return dataclasses.replace(self, **sections)

    def patch(self, rows: int, cols: int, *, substrate: bool = True,
              margin_px: int = 3) -> CameraModel:
        """Return the central ``rows`` × ``cols``-lenslet patch of this camera.

        The optics, pixel pitch and f-number are kept; the sensor is cut to the patch's
        micro-images (its outer size, a hexagonal grid's shifted rows included, times
        1 + f̄/S_i, in pixels) plus ``margin_px`` pixels a side,
        so small test cameras keep the full camera's geometry. Odd counts put a lenslet on the
        axis. ``substrate=False`` also removes the plate in front of the lenslets.
        """
        if rows < 1 or cols < 1:
            raise ConfigError(f"patch of {rows} x {cols} lenslets: expected at least 1 x 1")
        mla = dataclasses.replace(self.microlens_array, rows=int(rows), cols=int(cols),
                                  **({} if substrate else {"substrate": None}))
        # the array's outer size (a hexagonal grid's shifted rows included) in micro-images
        width, height = mla.extent
        spot_px = (1 + mla.sensor_distance / self.image_distance) / self.sensor.pixel_pitch
        sensor = dataclasses.replace(
            self.sensor, rows=int(math.ceil(height * spot_px - 1e-9)) + 2 * margin_px,
            cols=int(math.ceil(width * spot_px - 1e-9)) + 2 * margin_px)
        plate = "" if substrate or self.microlens_array.substrate is None else ", no substrate"
        return self.replace(sensor=sensor, microlens_array=mla,
                            name=f"{self.name}, {rows} x {cols}-lenslet patch{plate}")

    def with_image_distance(self, image_distance: float, *,
                            origin: str | None = None) -> CameraModel:
        """Return a copy with another effective image distance S_i,eff (metres).

        ``origin``: where it came from, for messages (:attr:`MainLens.image_distance_origin`;
        None: the camera file's key).
        """
        return self.replace(main_lens=dataclasses.replace(
            self.main_lens, image_distance=image_distance, image_distance_origin=origin))

    def to_dict(self) -> dict[str, Any]:
        """The camera as a config dictionary in the units of the TOML schema."""
        return camera_to_dict(self)

    def to_json(self) -> str:
        """The resolved camera config as JSON (stored with every product)."""
        return dumps(self.to_dict(), sort_keys=True)


# --------------------------------------------------------------------------------------------
# TOML schema (docs/design.md §7): validated here, converted to SI once
# --------------------------------------------------------------------------------------------


class _SensorCfg(StrictModel):
    rows: int = Field(gt=1)
    cols: int = Field(gt=1)
    pixel_pitch_um: float = Field(gt=0, allow_inf_nan=False)


class _SubstrateCfg(StrictModel):
    thickness_mm: float = Field(gt=0, allow_inf_nan=False)
    refractive_index: float = Field(ge=1.0, allow_inf_nan=False)


class _MLACfg(StrictModel):
    rows: int = Field(ge=1)
    cols: int = Field(ge=1)
    pitch_um: float = Field(gt=0, allow_inf_nan=False)
    focal_length_um: float = Field(gt=0, allow_inf_nan=False)
    sensor_distance_um: float = Field(gt=0, allow_inf_nan=False)
    grid: Literal["square", "hexagonal"] = "square"
    offset_um: tuple[float, float] = (0.0, 0.0)
    rotation_rad: float = Field(0.0, allow_inf_nan=False)
    back_side: Literal["physical", "thesis"] = "physical"
    substrate: _SubstrateCfg | None = None


class _MainLensCfg(StrictModel):
    focal_length_mm: float = Field(gt=0, allow_inf_nan=False)
    f_number: float = Field(gt=0, allow_inf_nan=False)
    image_distance_mm: float | None = Field(None, gt=0, allow_inf_nan=False)
    exit_pupil_offset_mm: float = Field(0.0, allow_inf_nan=False)


class _ExternalCfg(StrictModel):
    refractive_index: float = Field(ge=1.0, allow_inf_nan=False)
    outside_index: float = Field(1.0, ge=1.0, allow_inf_nan=False)
    medium_depth_mm: float = Field(0.0, ge=0, allow_inf_nan=False)


class _CameraCfg(StrictModel):
    name: str = "plenoptic camera"
    sensor: _SensorCfg
    microlens_array: _MLACfg
    main_lens: _MainLensCfg
    external_interface: _ExternalCfg | None = None


def camera_from_dict(cfg: dict, *, source: str = "camera config") -> CameraModel:
    """Validate a camera config dictionary (TOML schema, docs/design.md §7) and build the model.

    Raises
    ------
    ConfigError
        Naming every bad key with its value and the expectation.
    """
    if not isinstance(cfg, dict):
        raise ConfigError(f"{source}: expected a table of sections, got {type(cfg).__name__}")
    try:
        c = validate_table(_CameraCfg, cfg, source)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, source, _CameraCfg)) from None
    um, mm = 1e-6, 1e-3
    m = c.microlens_array
    try:
        substrate = (None if m.substrate is None else
                     Substrate(m.substrate.thickness_mm * mm, m.substrate.refractive_index))
        mla = MicrolensArray(rows=m.rows, cols=m.cols, pitch=m.pitch_um * um,
                             focal_length=m.focal_length_um * um,
                             sensor_distance=m.sensor_distance_um * um, grid=m.grid,
                             offset=(m.offset_um[0] * um, m.offset_um[1] * um),
                             rotation=m.rotation_rad, back_side=m.back_side, substrate=substrate)
        lens = MainLens(focal_length=c.main_lens.focal_length_mm * mm,
                        f_number=c.main_lens.f_number,
                        image_distance=(None if c.main_lens.image_distance_mm is None
                                        else c.main_lens.image_distance_mm * mm),
                        exit_pupil_offset=c.main_lens.exit_pupil_offset_mm * mm)
        ext = (None if c.external_interface is None else
               ExternalInterface(c.external_interface.refractive_index,
                                 c.external_interface.outside_index,
                                 c.external_interface.medium_depth_mm * mm))
        sensor = Sensor(c.sensor.rows, c.sensor.cols, c.sensor.pixel_pitch_um * um)
        return CameraModel(sensor=sensor, microlens_array=mla, main_lens=lens,
                           external_interface=ext, name=c.name, source={"path": source})
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def camera_to_dict(camera: CameraModel) -> dict[str, Any]:
    """Inverse of :func:`camera_from_dict`: the camera in config units (mm, µm)."""
    um, mm = 1e6, 1e3
    mla, lens, sen = camera.microlens_array, camera.main_lens, camera.sensor
    out: dict[str, Any] = {
        "name": camera.name,
        "sensor": {"rows": sen.rows, "cols": sen.cols, "pixel_pitch_um": sen.pixel_pitch * um},
        "microlens_array": {
            "rows": mla.rows, "cols": mla.cols, "pitch_um": mla.pitch * um,
            "focal_length_um": mla.focal_length * um,
            "sensor_distance_um": mla.sensor_distance * um, "grid": mla.grid,
            "offset_um": [mla.offset[0] * um, mla.offset[1] * um],
            "rotation_rad": mla.rotation, "back_side": mla.back_side,
        },
        "main_lens": {"focal_length_mm": lens.focal_length * mm, "f_number": lens.f_number,
                      "exit_pupil_offset_mm": lens.exit_pupil_offset * mm},
    }
    if mla.substrate is not None:
        out["microlens_array"]["substrate"] = {
            "thickness_mm": mla.substrate.thickness * mm,
            "refractive_index": mla.substrate.refractive_index}
    if lens.image_distance is not None:
        out["main_lens"]["image_distance_mm"] = lens.image_distance * mm
    if camera.external_interface is not None:
        e = camera.external_interface
        out["external_interface"] = {"refractive_index": e.refractive_index,
                                     "outside_index": e.outside_index,
                                     "medium_depth_mm": e.medium_depth * mm}
    return out


def read_toml(path: str | Path, what: str = "config") -> dict:
    """Read a TOML file, turning I/O and syntax errors into :class:`ConfigError`."""
    p = Path(path)
    if p.exists() and not p.is_file() and not p.is_dir():
        raise ConfigError(f"{what} file {str(p)!r} is not a regular file (a pipe, socket or "
                          "device): expected a TOML file")
    text = ""
    try:
        raw = p.read_bytes()
        _refuse_wide_text(raw, what, p)
        text = raw.decode("utf-8").lstrip("\ufeff")      # a byte-order mark is no key
        return tomllib.loads(text)
    except FileNotFoundError:
        raise ConfigError(f"{what} file {str(p)!r} not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{what} file {str(p)!r} is a folder: expected a TOML file") from None
    except tomllib.TOMLDecodeError as exc:
        mark = ""
        if "\ufeff" in text:
            line = text[:text.index("\ufeff")].count("\n") + 1
            mark = (f" (line {line} holds a byte-order mark, U+FEFF, where two files were "
                    "joined: remove it)")
        raise ConfigError(f"{what} file {str(p)!r} is not valid TOML: {exc}{mark}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{what} file {str(p)!r} is not UTF-8 text (byte "
                          f"0x{exc.object[exc.start]:02x} at offset {exc.start}): expected a "
                          "TOML file") from None
    except OSError as exc:
        raise ConfigError(f"{what} file {str(p)!r} cannot be read: {exc}") from None


def _refuse_wide_text(raw: bytes, what: str, path: Path) -> None:
    """Refuse UTF-16 or UTF-32 text by its byte-order mark, naming it (TOML is UTF-8)."""
    for mark, name in ((b"\xff\xfe\x00\x00", "UTF-32"), (b"\x00\x00\xfe\xff", "UTF-32"),
                       (b"\xff\xfe", "UTF-16"), (b"\xfe\xff", "UTF-16")):
        if raw.startswith(mark):
            raise ConfigError(f"{what} file {str(path)!r} is {name} text, not UTF-8 (it "
                              f"starts with the byte-order mark {mark.hex(' ').upper()}): save "
                              "it as UTF-8, with or without a byte-order mark")


def preset_names() -> list[str]:
    """Names of the camera presets shipped with the package."""
    return sorted(p.stem for p in PRESET_DIR.glob("*.toml"))


def load_camera(path_or_name: str | Path) -> CameraModel:
    """Load a camera from a TOML file, or a shipped preset by name (see :func:`preset_names`)."""
    if not isinstance(path_or_name, (str, Path)) or not str(path_or_name).strip():
        raise ConfigError(f"camera {path_or_name!r}: expected a camera TOML file or a preset "
                          f"name ({', '.join(preset_names())})")
    p = Path(path_or_name)
    if not p.exists() and p.suffix == "" and str(path_or_name) in preset_names():
        p = PRESET_DIR / f"{path_or_name}.toml"
    elif not p.exists():
        if p.suffix == ".toml" and p.stem in preset_names():   # configs/cameras/NAME.toml
            raise ConfigError(f"camera file {str(p)!r} not found: the preset {p.stem!r} ships "
                              f"inside plenopiv; name it {p.stem!r} (plenopiv presets "
                              f"{p.stem} --out FILE.toml writes a copy to edit)")
        raise ConfigError(f"camera file {str(p)!r} not found; presets: {', '.join(preset_names())}")
    return camera_from_dict(read_toml(p, "camera"), source=str(p))
