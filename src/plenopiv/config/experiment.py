"""Experiment configuration (TOML, docs/design.md §7): camera, volume and the processing options.

Every table but the camera and the volume is optional, every key has a default, a unit and a
meaning (docs/configuration.md); an unknown key is an error that names it and the valid ones. A
minimal file::

    camera = "cameras/auburn_135mm.toml"     # relative to this file, or a preset name

    [volume]
    x_mm = [-5, 5]
    y_mm = [-4, 4]
    z_mm = [-6, 6]
    voxel_mm = 0.25                           # or shape = [nz, ny, nx]
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, PlainValidator, ValidationError, create_model

from plenopiv.camera.grid import VolumeGrid, volume_from_dict
from plenopiv.camera.model import CameraModel, camera_from_dict, load_camera, read_toml
from plenopiv.errors import ConfigError
from plenopiv.particles.settings import ParticleSettings
from plenopiv.piv.settings import PIVSettings
from plenopiv.preprocess.settings import PreprocessSettings
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.settings import StrictModel, as_dict, format_validation_error, validate_table
from plenopiv.tracking.settings import TrackingSettings

__all__ = ["TABLES", "Experiment", "ExperimentFile", "experiment_from_dict", "load_experiment"]


def _piv_table(value) -> PIVSettings:
    """``[piv]``: the table is :class:`~plenopiv.piv.settings.PIVSettings` (its own checks)."""
    if isinstance(value, PIVSettings):
        return value
    if not isinstance(value, dict):
        raise ValueError(f"expected a table, got {value!r}")
    valid = [f.name for f in dataclasses.fields(PIVSettings)]
    unknown = sorted(set(value) - set(valid))
    if unknown:
        raise ValueError(f"unknown key {unknown[0]}; valid keys here: {', '.join(sorted(valid))}")
    windows = value.get("windows")
    if isinstance(windows, list):     # TOML arrays: a list of windows or one window
        value = {**value, "windows": tuple(tuple(w) if isinstance(w, list) else w
                                           for w in windows)}
    return PIVSettings(**value)


#: The ``[piv]`` table, built by :class:`~plenopiv.piv.settings.PIVSettings` itself.
PIVTable = Annotated[PIVSettings, PlainValidator(_piv_table)]


class BoxMask(StrictModel):
    """One ``[[mask.box]]``: a box in volume coordinates (mm, those of ``[volume]``).

    masked : "inside" (default: the box is a body in the flow) | "outside" (the flow is
        inside the box; everything else is masked).
    """

    x_mm: tuple[float, float]
    y_mm: tuple[float, float]
    z_mm: tuple[float, float]
    masked: Literal["inside", "outside"] = "inside"


class CylinderMask(StrictModel):
    """One ``[[mask.cylinder]]``: a circular cylinder along a volume axis (mm).

    axis : "x" | "y" | "z", the cylinder's axis.
    centre_mm : position of the axis in the two other coordinates, in x, y, z order
        (axis "y": ``[x, z]``; axis "x": ``[y, z]``; axis "z": ``[x, y]``).
    radius_mm : radius (> 0).
    length_mm : ``[lo, hi]`` extent along the axis (default: unbounded).
    masked : "inside" (default: a cylinder in the flow) | "outside" (a pipe: the flow is
        inside).
    """

    axis: Literal["x", "y", "z"]
    centre_mm: tuple[float, float]
    radius_mm: float = Field(gt=0, allow_inf_nan=False)
    length_mm: tuple[float, float] | None = None
    masked: Literal["inside", "outside"] = "inside"


class MaskConfig(StrictModel):
    """``[mask]``: what to leave out.

    image : a boolean image of the sensor's shape (TIFF, PNG, ``.npy`` or ``file.h5:/path``,
        relative to the experiment file): non-zero pixels (reflections, a model in the view)
        are left out of the reconstruction (their rows of the system are dropped; they are
        not taken as dark).
    volume : a boolean array of the ``[volume]`` grid's shape ``[nz, ny, nx]`` (``.npy`` or
        ``file.h5:/path``): true voxels are outside the flow.
    box, cylinder : geometric volume masks (``[[mask.box]]``, ``[[mask.cylinder]]``), added
        to ``volume``. Masked voxels are zeroed before the PIV; a vector whose window centre
        is masked is NaN, not valid and flagged (``/flag`` bit 4).
    """

    image: str | None = None
    volume: str | None = None
    box: list[BoxMask] = []
    cylinder: list[CylinderMask] = []


class ImagesConfig(StrictModel):
    """``[images]``: the image pairs of ``plenopiv run``.

    a, b : glob patterns of the first and second exposures, or
    pairs : glob pattern of HDF5 files each holding ``/image_a`` and ``/image_b``.
    pair_by : how a and b pair up: "auto" (default), "stem" (the parts matched by the
        wildcards agree) or "order" (sorted order); see :func:`plenopiv.batch.discover_pairs`.
    dt_s : time between the exposures, seconds (velocity in m/s when given).
    calibration : the calibration product (.h5), relative to the experiment file.
    """

    a: str | None = None
    b: str | None = None
    pairs: str | None = None
    pair_by: Literal["auto", "stem", "order"] = "auto"
    dt_s: float | None = Field(None, gt=0)
    calibration: str | None = None


class BatchConfig(StrictModel):
    """``[batch]``: where the pairs run.

    cluster : "local" | "slurm" | a scheduler address ("tcp://host:8786").
    workers, threads_per_worker : local cluster size (default: cores, one thread each).
    queue, cores, memory, walltime, jobs : SLURM job settings (dask-jobqueue).
    connect_timeout_s : seconds a scheduler address has to answer as a dask scheduler.
    """

    cluster: str = "local"
    workers: int | None = Field(None, ge=1)
    threads_per_worker: int | None = Field(None, ge=1)
    retries: int = Field(2, ge=0)
    connect_timeout_s: float = Field(10.0, gt=0, allow_inf_nan=False)
    queue: str | None = None
    cores: int | None = Field(None, ge=1)
    memory: str | None = None
    walltime: str | None = None
    jobs: int | None = Field(None, ge=1)


class OutputConfig(StrictModel):
    """``[output]``: products.

    directory : output folder (relative to the experiment file).
    vtk : also write .vti volumes/vectors for ParaView.
    png : also write PNG figures.
    weights_cache : folder of the voxel-pixel weight cache ("" to disable).
    """

    directory: str = "out"
    vtk: bool = True
    png: bool = True
    weights_cache: str = ".plenopiv-cache"


@dataclass(frozen=True)
class Experiment:
    """A resolved experiment configuration: the camera, the volume and one field per table.

    The tables (:data:`TABLES`) are declared here only; the file's model
    (:data:`ExperimentFile`) is derived from them. ``base_dir`` is the folder relative paths
    of the file resolve against, ``source`` the file's tables as read.
    """

    camera: CameraModel
    volume: VolumeGrid
    reconstruction: ReconstructionSettings = ReconstructionSettings()
    particles: ParticleSettings = ParticleSettings()
    piv: PIVTable = PIVSettings()
    images: ImagesConfig = ImagesConfig()
    batch: BatchConfig = BatchConfig()
    output: OutputConfig = OutputConfig()
    tracking: TrackingSettings = TrackingSettings()
    mask: MaskConfig = MaskConfig()
    preprocess: PreprocessSettings | None = None
    base_dir: Path = Path(".")
    source: dict = field(default_factory=dict, compare=False, repr=False)

    def path(self, relative: str | None) -> Path | None:
        """Return a path of the config, resolved against the experiment file's folder."""
        if relative is None:
            return None
        p = Path(relative)
        return p if p.is_absolute() else self.base_dir / p

    def to_dict(self) -> dict:
        """Return the resolved configuration (camera in full), for product attributes."""
        tables = {name: getattr(self, name) for name in TABLES}
        return {"camera": self.camera.to_dict(), "volume": self.volume.to_dict(),
                **{name: None if value is None else as_dict(value)
                   for name, value in tables.items()}}


TABLES = ("reconstruction", "particles", "piv", "images", "batch", "output", "tracking", "mask",
          "preprocess")
"""The optional tables of an experiment file, each one field of :class:`Experiment`."""


def _file_model():
    """The TOML model of an experiment file, derived from :class:`Experiment`'s tables.

    Each table is declared once, on :class:`Experiment` (its type and default); the file adds
    the camera (a preset name, a path or an inline table) and the volume (a table).
    """
    hints = typing.get_type_hints(Experiment, include_extras=True)
    tables = {f.name: (hints[f.name], f.default) for f in dataclasses.fields(Experiment)
              if f.name in TABLES}
    return create_model("ExperimentFile", __base__=StrictModel, camera=(str | dict, ...),
                        volume=(dict, ...), **tables)


ExperimentFile = _file_model()


def experiment_from_dict(cfg: dict, *, base_dir: Path = Path("."),
                         source: str = "experiment config") -> Experiment:
    """Validate an experiment config dictionary and resolve the camera and the grid."""
    try:
        c = validate_table(ExperimentFile, cfg, source)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, source, ExperimentFile)) from None
    if isinstance(c.camera, dict):
        camera = camera_from_dict(c.camera, source=f"{source} [camera]")
    else:
        p = Path(c.camera)
        cand = p if p.is_absolute() else base_dir / p
        camera = load_camera(cand if cand.exists() else c.camera)
    grid = volume_from_dict(c.volume, source=source)
    return Experiment(camera, grid, base_dir=base_dir, source=cfg,
                      **{name: getattr(c, name) for name in TABLES})


def load_experiment(path: str | Path) -> Experiment:
    """Load an experiment TOML file (relative paths inside resolve against its folder)."""
    p = Path(path)
    return experiment_from_dict(read_toml(p, "experiment"), base_dir=p.parent, source=str(p))
