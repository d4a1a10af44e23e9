"""The volume product: a reconstructed volume and its particles, written and read as HDF5.

Datasets ``/volume`` (z, y, x), ``/x``, ``/y``, ``/z`` (corrected depth), ``/z_effective``
and ``/particles/*``, in SI units with CF dimension scales (docs/design.md §7).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plenopiv.camera.corrections import DepthCorrection
from plenopiv.camera.grid import VolumeGrid
from plenopiv.errors import ReconstructionError
from plenopiv.products.hdf5 import cf_axes, open_product, write_h5


@dataclass(frozen=True)
class VolumeResult:
    """A reconstructed volume and its particles.

    Attributes
    ----------
    volume : (nz, ny, nx) float32
        Reconstructed intensity on ``grid`` (effective coordinates).
    grid : VolumeGrid
        Effective (air-equivalent) grid of the reconstruction.
    correction : DepthCorrection
        From effective to physical depth.
    particle_position_effective : (N, 3)
        Particle (x, y, z) in effective coordinates, metres.
    particle_position : (N, 3)
        The same after the depth corrections, metres.
    particle_intensity, particle_size : (N,), (N, 3)
        Integrated intensity; blob σ along (x, y, z) in metres (effective).
    timings : dict
        Seconds per stage.
    particle_centroid_effective : (N, 3) or None
        The volume's own estimate of each position (``[particles] method`` on the voxels),
        effective coordinates, metres, where the positions come from the light field
        (``[particles] position = "light_field"``); None where they are the volume's.
    """

    volume: np.ndarray
    grid: VolumeGrid
    correction: DepthCorrection
    particle_position_effective: np.ndarray
    particle_position: np.ndarray
    particle_intensity: np.ndarray
    particle_size: np.ndarray
    timings: dict = field(default_factory=dict)
    particle_centroid_effective: np.ndarray | None = None

    @property
    def volume_position_effective(self) -> np.ndarray:
        """The volume's own estimate of the particle positions (N, 3), effective, metres.

        The centroids where the positions came from the light field, else the positions.
        """
        if self.particle_centroid_effective is None:
            return self.particle_position_effective
        return self.particle_centroid_effective

    def volume_peaks(self) -> tuple[np.ndarray, np.ndarray]:
        """``(centroid (K, 3), intensity (K,))`` of the volume's peaks, effective metres.

        The particles split from one peak (``[particles] split_brighter``) share its centroid:
        each peak is listed once, in the particles' order, with their intensities summed.
        """
        cen = np.asarray(self.volume_position_effective, float).reshape(-1, 3)
        inten = np.asarray(self.particle_intensity, float).reshape(-1)
        if len(cen) == 0:
            return cen, inten
        _, first, which = np.unique(cen, axis=0, return_index=True, return_inverse=True)
        order = np.argsort(first)
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        return cen[first[order]], np.bincount(rank[which.reshape(-1)], weights=inten,
                                              minlength=len(order))

    @property
    def z_corrected(self) -> np.ndarray:
        """Physical depth of each voxel layer, metres."""
        return self.correction.depth(self.grid.z)

    def save(self, path: str | Path, *, config: dict | None = None, extra_attrs=None,
             provenance: dict | None = None) -> Path:
        """Write the volume product (docs/design.md §7), atomically.

        ``provenance``: what made it (:func:`~plenopiv.products.provenance.make_provenance`).
        """
        ds = {"/volume": self.volume.astype(np.float32), "/x": self.grid.x, "/y": self.grid.y,
              "/z": self.z_corrected, "/z_effective": self.grid.z,
              "/particles/position_m": self.particle_position,
              "/particles/position_effective_m": self.particle_position_effective,
              "/particles/intensity": self.particle_intensity,
              "/particles/size_m": self.particle_size}
        if self.particle_centroid_effective is not None:
            ds["/particles/centroid_effective_m"] = self.particle_centroid_effective
        units = {k: "m" for k in ("/x", "/y", "/z", "/z_effective", "/particles/position_m",
                                  "/particles/position_effective_m", "/particles/size_m",
                                  "/particles/centroid_effective_m")}
        # the voxel values are light energies in image counts (W E = I, with W the fraction
        # of a voxel's light reaching each pixel): dimensionless in SI
        units.update({"/volume": "1", "/particles/intensity": "1"})
        attrs = {"n_particles": len(self.particle_position), "voxel_m": np.array(self.grid.voxel),
                 "depth_correction_scale": self.correction.scale,
                 "depth_correction_external": self.correction.external,
                 "depth_correction_internal": self.correction.internal,
                 "volume_axes": "z, y, x", "Conventions": "CF-1.8",
                 "particle_positions": ("volume" if self.particle_centroid_effective is None
                                        else "light_field"), **(extra_attrs or {})}
        return write_h5(path, ds, attrs=attrs, units=units, config=config, kind="volume",
                        may_be_nan=NAN_DATASETS,
                        finalize=_cf_volume, provenance=provenance)


#: Datasets of the volume product that may hold NaN: a size the Gaussian fit could not measure
#: along an axis (a peak whose samples are not concave there).
NAN_DATASETS = ("/particles/size_m",)


def load_volume(path: str | Path) -> VolumeResult:
    """Read a volume product written by :meth:`VolumeResult.save`.

    Every array is checked finite (:meth:`~plenopiv.products.hdf5.ProductFile.array`): a
    damaged product is refused naming the file and the dataset.
    """
    with open_product(path, "volume", ReconstructionError) as fh:
        x, y, ze = fh.array("/x"), fh.array("/y"), fh.array("/z_effective")
        fh.array("/z")
        vol = fh.array("/volume")
        corr = DepthCorrection(fh.number("depth_correction_external"),
                               fh.number("depth_correction_internal"))
        pos = fh.array("/particles/position_m")
        pos_e = fh.array("/particles/position_effective_m")
        inten = fh.array("/particles/intensity")
        size = fh.array("/particles/size_m", allow_nan="/particles/size_m" in NAN_DATASETS)
        cen = (fh.array("/particles/centroid_effective_m")
               if "/particles/centroid_effective_m" in fh else None)
    step = [a[1] - a[0] if len(a) > 1 else 1.0 for a in (x, y, ze)]
    grid = VolumeGrid((float(x[0]), float(y[0]), float(ze[0])), tuple(float(v) for v in step),
                      vol.shape)
    return VolumeResult(vol, grid, corr, pos_e, pos, inten, size,
                        particle_centroid_effective=cen)


def volume_attribute(path: str | Path, name: str) -> str | None:
    """The root attribute ``name`` of a volume product, or None where it has none."""
    with open_product(path, "volume", ReconstructionError) as fh:
        value = fh.attrs.get(name)
    if isinstance(value, bytes):
        value = value.decode()
    return None if value is None else str(value)


def _cf_volume(fh) -> None:
    """Dimension scales and long names of an open volume product (xarray sees x, y, z)."""
    cf_axes(fh)
    fh["z"].attrs["long_name"] = "depth Z from the nominal focal plane, corrected"
    for dim, axis in enumerate(("z", "y", "x")):
        fh["volume"].dims[dim].attach_scale(fh[axis])
    fh["z_effective"].dims[0].attach_scale(fh["z"])
    fh["z_effective"].attrs["long_name"] = "effective (air-equivalent) depth of each layer"
    fh["volume"].attrs["long_name"] = ("reconstructed light energy per voxel, in image "
                                       "counts")
    fh["particles/intensity"].attrs["long_name"] = ("integrated light energy of each "
                                                    "particle, in image counts")
