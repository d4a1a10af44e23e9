"""Depth corrections: from effective (reconstruction) depth to physical depth.

:class:`DepthCorrection` scales depth about the nominal focal plane for a flat external
interface (thesis Eq. 4.7) and for the substrate of the "thesis" back side (Eq. 5.1); X and Y
are unchanged. The corrections are exactly invertible and act on particle tables and on a
volume's Z axis.

See docs/methods.md#depth-corrections.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plenopiv.camera.model import CameraModel
from plenopiv.errors import ConfigError


@dataclass(frozen=True)
class DepthCorrection:
    """Physical depth = ``scale`` × effective depth, about the nominal focal plane.

    Attributes
    ----------
    external : float
        n1/n2 of the external interface (1 without one).
    internal : float
        n3/n4 of the internal plate (1 when none is needed).
    """

    external: float = 1.0
    internal: float = 1.0

    def __post_init__(self):
        for name in ("external", "internal"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ConfigError(f"depth correction {name} = {v!r}: expected a positive factor")

    @property
    def scale(self) -> float:
        """Overall factor from effective to physical depth."""
        return self.external * self.internal

    @classmethod
    def for_camera(cls, camera: CameraModel, *, internal: str = "auto") -> DepthCorrection:
        """The corrections a camera needs.

        Parameters
        ----------
        internal : {"auto", "none", "plate"}
            "auto": 1/n for the "thesis" back side with a substrate, else none; "plate": 1/n
            whatever the back side; "none": no internal correction.
        """
        if internal not in ("auto", "none", "plate"):
            raise ConfigError(f"internal correction = {internal!r}: expected 'auto', 'none' "
                              "or 'plate'")
        ext = camera.external_interface
        external = 1.0 if ext is None else ext.refractive_index / ext.outside_index
        sub = camera.microlens_array.substrate
        needs = sub is not None and (internal == "plate" or (
            internal == "auto" and camera.microlens_array.back_side == "thesis"))
        return cls(external=external, internal=(1.0 / sub.refractive_index) if needs else 1.0)

    def depth(self, effective_depth):
        """Physical depth (metres) from effective depth (metres)."""
        return np.asarray(effective_depth, dtype=float) * self.scale

    def effective(self, depth):
        """Inverse of :meth:`depth`."""
        return np.asarray(depth, dtype=float) / self.scale

    def points(self, effective_points) -> np.ndarray:
        """Correct (N, 3) points (x, y, z): z scaled, x and y unchanged; a new array."""
        p = np.array(effective_points, dtype=float, ndmin=2)
        p[:, 2] *= self.scale
        return p

    def to_dict(self) -> dict:
        """The factors, for product attributes."""
        return {"external_n1_over_n2": self.external, "internal_n3_over_n4": self.internal,
                "scale": self.scale}
