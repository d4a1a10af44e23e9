"""The reconstruction grid: a box of voxels in volume coordinates (X, Y, Z), metres.

Volumes are indexed ``[z, y, x]``; voxel ``[k, j, i]`` has its centre at
``(x[i], y[j], z[k])``. Z is measured from the nominal focal plane, + away from the camera;
the reconstruction works in effective (air-equivalent) depth, see
:mod:`plenopiv.camera.corrections`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import Field, ValidationError, model_validator

from plenopiv.errors import ConfigError
from plenopiv.settings import StrictModel, format_validation_error, validate_table

#: More voxels than this is refused at once: the voxel-pixel weights index voxels with
#: 32-bit integers, and a float32 volume of 2^31 voxels alone is 8.6 GB.
MAX_VOXELS = float(2 ** 31 - 1)


@dataclass(frozen=True)
class VolumeGrid:
    """A regular voxel grid.

    Attributes
    ----------
    origin : tuple of float
        ``(x, y, z)`` of the centre of voxel ``[0, 0, 0]``, metres.
    voxel : tuple of float
        Voxel edges ``(dx, dy, dz)``, metres.
    shape : tuple of int
        ``(nz, ny, nx)``.
    """

    origin: tuple[float, float, float]
    voxel: tuple[float, float, float]
    shape: tuple[int, int, int]

    def __post_init__(self):
        if any(n < 1 for n in self.shape):
            raise ConfigError(f"[volume] shape = {list(self.shape)}: expected at least one "
                              "voxel along every axis")
        if not all(v > 0 and math.isfinite(v) for v in self.voxel):
            raise ConfigError(f"[volume] voxel size = {list(self.voxel)} m: expected > 0")

    @classmethod
    def from_bounds(cls, x, y, z, *, voxel=None, shape=None) -> VolumeGrid:
        """A grid covering the boxes ``x = (lo, hi)``, ``y``, ``z`` (metres).

        Give either ``voxel`` (a float, or ``(dx, dy, dz)``; the counts are rounded so that
        the voxels fill the box) or ``shape = (nz, ny, nx)``.
        """
        bounds = np.array([x, y, z], dtype=float)
        if bounds.shape != (3, 2):
            raise ConfigError(f"[volume] bounds x, y, z = {bounds.tolist()} m: expected "
                              "[lo, hi] with hi > lo on every axis")
        for axis, (lo, hi) in zip("xyz", bounds, strict=True):
            if not (np.isfinite(lo) and np.isfinite(hi)):
                shown = [float(lo) * 1e3, float(hi) * 1e3]
                raise ConfigError(f"[volume] {axis}_mm = {shown}: expected finite numbers "
                                  "[lo, hi]")
            if not hi > lo:
                raise ConfigError(f"[volume] {axis}_mm = [{lo * 1e3:g}, {hi * 1e3:g}]: expected "
                                  "[lo, hi] with hi > lo")
        span = bounds[:, 1] - bounds[:, 0]
        if (voxel is None) == (shape is None):
            raise ConfigError("[volume]: give exactly one of voxel_mm and shape")
        if shape is not None:
            nz, ny, nx = (int(v) for v in shape)
            counts = np.array([nx, ny, nz])
        else:
            v = np.broadcast_to(np.asarray(voxel, dtype=float), (3,))
            if not np.all(np.isfinite(v) & (v > 0)):
                raise ConfigError(f"[volume] voxel_mm = {(np.asarray(voxel) * 1e3).tolist()}: "
                                  "expected finite values > 0")
            for axis, vi, si in zip("xyz", v, span, strict=True):
                if vi > si * (1 + 1e-9):
                    raise ConfigError(
                        f"[volume] voxel_mm = {vi * 1e3:g} is larger than the box along "
                        f"{axis} ({si * 1e3:g} mm, {axis}_mm): expected a voxel smaller than "
                        "the box (several voxels along every axis)")
            n = span / v
            if float(np.prod(n)) > MAX_VOXELS:
                raise ConfigError(
                    f"[volume] voxel_mm = {(v * 1e3).tolist()} on a box of "
                    f"{(span * 1e3).tolist()} mm gives {float(np.prod(n)):.3g} voxels: "
                    f"expected at most {MAX_VOXELS:.0e} (use larger voxels or a smaller box)")
            counts = np.maximum(1, np.rint(n)).astype(int)
        if np.any(counts < 1):
            raise ConfigError(f"[volume] shape = {counts[::-1].tolist()}: expected at least one "
                              "voxel along every axis")
        if float(np.prod(counts.astype(float))) > MAX_VOXELS:
            raise ConfigError(f"[volume] shape = {counts[::-1].tolist()} is "
                              f"{float(np.prod(counts.astype(float))):.3g} voxels: expected at "
                              f"most {MAX_VOXELS:.0e} (use larger voxels or a smaller box)")
        size = span / counts
        origin = bounds[:, 0] + size / 2
        return cls(tuple(origin), tuple(size), (int(counts[2]), int(counts[1]), int(counts[0])))

    @property
    def n_voxels(self) -> int:
        """Number of voxels."""
        return int(np.prod(self.shape))

    def axis(self, name: str) -> np.ndarray:
        """Voxel-centre coordinates along ``"x"``, ``"y"`` or ``"z"``, metres."""
        i = "xyz".index(name)
        n = self.shape[2 - i]
        return self.origin[i] + self.voxel[i] * np.arange(n)

    @property
    def x(self) -> np.ndarray:
        """Voxel-centre x coordinates, metres."""
        return self.axis("x")

    @property
    def y(self) -> np.ndarray:
        """Voxel-centre y coordinates, metres."""
        return self.axis("y")

    @property
    def z(self) -> np.ndarray:
        """Voxel-centre z (depth Z) coordinates, metres."""
        return self.axis("z")

    @property
    def bounds(self) -> np.ndarray:
        """Outer box ``[[xlo, xhi], [ylo, yhi], [zlo, zhi]]``, metres."""
        o, v = np.array(self.origin), np.array(self.voxel)
        n = np.array(self.shape[::-1])
        return np.stack([o - v / 2, o + v * (n - 0.5)], axis=1)

    def to_dict(self) -> dict:
        """The grid in config units (mm)."""
        b = self.bounds * 1e3
        return {"x_mm": b[0].tolist(), "y_mm": b[1].tolist(), "z_mm": b[2].tolist(),
                "shape": list(self.shape)}

    def key(self) -> str:
        """A stable text key of the grid (for caches)."""
        return f"o={np.round(self.origin, 12).tolist()} v={np.round(self.voxel, 12).tolist()} " \
               f"n={list(self.shape)}"


class _VolumeCfg(StrictModel):
    # non-finite bounds are refused by volume_from_dict, naming them in millimetres
    model_config = {**StrictModel.model_config, "allow_inf_nan": True}
    x_mm: tuple[float, float]
    y_mm: tuple[float, float]
    z_mm: tuple[float, float]
    voxel_mm: float | tuple[float, float, float] | None = Field(None)
    shape: tuple[int, int, int] | None = None

    @model_validator(mode="after")
    def _one_size(self):
        if (self.voxel_mm is None) == (self.shape is None):
            raise ValueError("give exactly one of voxel_mm and shape")
        return self


#: The form of the ``[volume]`` keys, appended to every error about them.
VOLUME_FORM = ("; expected x_mm, y_mm, z_mm = [lo, hi] (mm, hi > lo), and voxel_mm = an edge "
               "or [dx, dy, dz] (mm) or shape = [nz, ny, nx], e.g. x_mm = [-7, 7], "
               "voxel_mm = 0.13")


def volume_from_dict(cfg: dict, *, source: str = "[volume]") -> VolumeGrid:
    """Validate a ``[volume]`` table (x_mm, y_mm, z_mm, voxel_mm or shape) and build the grid."""
    vox = cfg.get("voxel_mm") if isinstance(cfg, dict) else None
    if isinstance(vox, (list, tuple)) and len(vox) != 3:
        raise ConfigError(f"{source}: [volume] voxel_mm = {list(vox)!r}: expected one number "
                          "(cubic voxels) or a list of 3 numbers [dx, dy, dz]")
    shp = cfg.get("shape") if isinstance(cfg, dict) else None
    if shp is not None and not (isinstance(shp, (list, tuple)) and len(shp) == 3):
        raise ConfigError(f"{source}: [volume] shape = {shp!r}: expected a list of 3 voxel "
                          "counts [nz, ny, nx]")
    try:
        c = validate_table(_VolumeCfg, cfg, source)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, source, _VolumeCfg)
                          .replace(f"{source}: ", f"{source}: [volume] ") + VOLUME_FORM) from None
    mm = 1e-3
    voxel = None if c.voxel_mm is None else np.asarray(c.voxel_mm, float) * mm
    try:
        return VolumeGrid.from_bounds(np.array(c.x_mm) * mm, np.array(c.y_mm) * mm,
                                      np.array(c.z_mm) * mm, voxel=voxel, shape=c.shape)
    except ConfigError as exc:
        if source == "[volume]":
            raise
        raise ConfigError(f"{source}: {exc}") from None
