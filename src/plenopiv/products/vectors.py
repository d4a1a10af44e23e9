"""The vectors product: a 3-D vector field with its quality and uncertainty, as HDF5 and VTK.

``/u, /v, /w`` (z, y, x) in metres or m/s, their uncertainties, per-vector quality
(:data:`QUALITY`) and CF dimension scales ``/x, /y, /z`` (docs/design.md §7); a ``.vti`` beside
it for ParaView.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plenopiv.camera.corrections import DepthCorrection
from plenopiv.camera.grid import VolumeGrid
from plenopiv.errors import ConfigError, ReconstructionError
from plenopiv.products.files import atomic_path
from plenopiv.products.hdf5 import cf_axes, check_writable, open_product, write_h5


def check_dt(dt, what: str = "dt") -> float | None:
    """``dt`` (seconds between the exposures) as a float; None stays None (displacements).

    Raises :class:`~plenopiv.errors.ConfigError` unless it is a finite number > 0.
    """
    if dt is None:
        return None
    if isinstance(dt, bool) or not isinstance(dt, (int, float, np.integer, np.floating)):
        raise ConfigError(f"{what} = {dt!r}: expected a time in seconds (a number > 0) or None")
    if not (math.isfinite(float(dt)) and dt > 0):
        raise ConfigError(f"{what} = {float(dt)!r} s: expected a finite time > 0 between the "
                          "two exposures")
    return float(dt)


#: Largest velocity a product holds, m/s: a dt that makes more of a displacement is wrong.
MAX_VELOCITY_M_S = 1e12


def check_velocity(u, v, w, dt) -> None:
    """Refuse a ``dt`` that makes velocities beyond :data:`MAX_VELOCITY_M_S`, naming both."""
    if dt is None:
        return
    with np.errstate(invalid="ignore"):
        largest = max((float(np.nanmax(np.abs(np.asarray(c, float)), initial=0.0))
                       for c in (u, v, w)), default=0.0)
    if largest / dt > MAX_VELOCITY_M_S:
        raise ConfigError(f"dt = {dt!r} s turns displacements of up to {largest:.3g} m into "
                          f"velocities of {largest / dt:.3g} m/s (more than "
                          f"{MAX_VELOCITY_M_S:.0e}): expected the time between the exposures "
                          "in seconds")


#: Per-vector quality arrays of the vectors product: name -> (dtype, units, long name).
QUALITY = {
    "valid": (np.int8, "1", "1: valid vector; 0: rejected (see flag)"),
    "flag": (np.uint8, "1", "why a vector was rejected, sum of 1: normalised median test, "
             "2: empty window (no particles), 4: window centre in the volume mask, 8: fewer "
             "particles in a window than [piv] min_particles_per_window; 0: valid"),
    "particles_per_window": (np.int32, "1", "particles in the vector's windows of the last "
                             "pass, the fewer of volume A's and B's; -1: not counted"),
    "replaced": (np.int8, "1", "1: rejected vector filled from its neighbours"),
    "peak_ratio": (np.float32, "1", "correlation peak ratio, primary over secondary peak"),
    "snr": (np.float32, "1", "correlation peak ratio (same as peak_ratio)"),
    "peak_height": (np.float32, "1", "correlation peak height (correlation coefficient)"),
}


@dataclass(frozen=True)
class VectorResult:
    """A 3-D vector field in physical coordinates.

    Attributes
    ----------
    x, y, z : 1-D arrays
        Window centres, metres; z is the physical depth (depth corrections applied).
    u, v, w : (nz, ny, nx)
        Displacement along x, y, z in metres (w corrected to physical depth); NaN where a
        rejected vector was not replaced or is masked.
    valid : (nz, ny, nx) bool
    snr : (nz, ny, nx)
        Correlation peak ratio (primary over secondary peak); also :attr:`peak_ratio`.
    dt : float or None
        Seconds between exposures; velocity = displacement / dt.
    n_replaced : int
    peak_height : (nz, ny, nx)
        Correlation peak height (correlation coefficient).
    flag : (nz, ny, nx) uint8
        Rejection reasons (bits of :mod:`plenopiv.piv`: 1 median test, 2 empty, 4 masked,
        8 too few particles).
    particles_per_window : (nz, ny, nx) int32
        Particles in each vector's windows, the fewer of A's and B's; -1 where not counted.
    replaced : (nz, ny, nx) bool
        Rejected vectors filled from their neighbours.
    u_uncertainty, v_uncertainty, w_uncertainty : (nz, ny, nx)
        Standard uncertainty of u, v, w, metres (w's in physical depth).
    uncertainty_method : str
        ``"response"`` or ``"correlation"`` (see :mod:`plenopiv.piv.uncertainty`).
    grid : VolumeGrid or None
        The voxel grid the volumes were correlated on, in physical coordinates (its depth
        corrected like ``z``); None where unknown. Its voxel is the unit of the field's
        figures in voxels (``plenopiv compare``).
    window_vox : (wz, wy, wx) or None
        The interrogation window of the last pass, voxels; None where unknown.
    w_gain_error : (nz,) or None
        The chain's relative gain error of w per layer (dimensionless,
        :meth:`plenopiv.piv.response.Response.gain_error`), whose term ``w_gain_error · |w|``
        the response puts into ``w_uncertainty``; None without a response. For the
        continuity fit's weights (:func:`plenopiv.workflow.correlation.fitted_to_continuity`);
        not saved.
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    u: np.ndarray
    v: np.ndarray
    w: np.ndarray
    valid: np.ndarray
    snr: np.ndarray
    dt: float | None = None
    n_replaced: int = 0
    peak_height: np.ndarray | None = None
    flag: np.ndarray | None = None
    replaced: np.ndarray | None = None
    u_uncertainty: np.ndarray | None = None
    v_uncertainty: np.ndarray | None = None
    w_uncertainty: np.ndarray | None = None
    uncertainty_method: str = "correlation"
    grid: VolumeGrid | None = None
    window_vox: tuple[int, int, int] | None = None
    particles_per_window: np.ndarray | None = None
    w_gain_error: np.ndarray | None = dataclasses.field(default=None, compare=False, repr=False)

    def __post_init__(self):
        object.__setattr__(self, "dt", check_dt(self.dt, "VectorResult dt"))
        check_velocity(self.u, self.v, self.w, self.dt)
        shape = np.shape(self.u)
        valid = np.asarray(self.valid, bool)
        defaults = {"peak_height": np.full(shape, np.nan),
                    "flag": np.where(valid, 0, 1).astype(np.uint8),
                    "replaced": ~valid & np.isfinite(np.asarray(self.u, float)),
                    "u_uncertainty": np.full(shape, np.nan),
                    "v_uncertainty": np.full(shape, np.nan),
                    "w_uncertainty": np.full(shape, np.nan),
                    "particles_per_window": np.full(shape, -1, np.int32)}
        for name, value in defaults.items():
            if getattr(self, name) is None:
                object.__setattr__(self, name, value)

    @property
    def peak_ratio(self) -> np.ndarray:
        """Correlation peak ratio (the same array as ``snr``)."""
        return self.snr

    @classmethod
    def from_field(cls, field, correction: DepthCorrection, dt=None, *,
                   uncertainty_method: str = "correlation",
                   grid: VolumeGrid | None = None, w_gain_error=None) -> VectorResult:
        """Convert a :class:`plenopiv.piv.VectorField` of effective coordinates.

        ``grid``: the effective grid the volumes were reconstructed on (kept with its depth
        corrected, :attr:`grid`); ``w_gain_error``: :attr:`w_gain_error`.
        """
        scale = abs(correction.scale)
        physical = None if grid is None else physical_grid(grid, correction)
        return cls(np.asarray(field.x), np.asarray(field.y), correction.depth(field.z),
                   np.asarray(field.u), np.asarray(field.v), correction.depth(field.w),
                   np.asarray(field.valid), np.asarray(field.snr), dt, int(field.n_replaced),
                   peak_height=np.asarray(field.correlation), flag=np.asarray(field.flag),
                   replaced=np.asarray(field.replaced),
                   u_uncertainty=np.asarray(field.u_uncertainty),
                   v_uncertainty=np.asarray(field.v_uncertainty),
                   w_uncertainty=np.asarray(field.w_uncertainty) * scale,
                   uncertainty_method=uncertainty_method, grid=physical,
                   window_vox=tuple(int(n) for n in field.settings.windows[-1]),
                   particles_per_window=np.asarray(field.particles_per_window),
                   w_gain_error=None if w_gain_error is None else np.asarray(w_gain_error,
                                                                             float))

    def _quality(self) -> dict:
        return {"valid": self.valid, "flag": self.flag, "replaced": self.replaced,
                "particles_per_window": self.particles_per_window,
                "peak_ratio": self.snr, "snr": self.snr, "peak_height": self.peak_height}

    def save(self, path: str | Path, *, config: dict | None = None, vtk: bool = False,
             extra_attrs=None, provenance: dict | None = None) -> list[Path]:
        """Write the vectors product (CF style HDF5), and a ``.vti`` for ParaView if asked.

        ``/u, /v, /w`` are displacements in metres, or velocities in m/s when ``dt`` is set
        (their ``units`` attribute says which); ``/u_uncertainty`` etc. their standard
        uncertainties in the same units; per-vector quality in ``/valid``, ``/flag``,
        ``/replaced``, ``/particles_per_window``, ``/peak_ratio`` (also ``/snr``) and
        ``/peak_height``. ``provenance``: what made it
        (:func:`~plenopiv.products.provenance.make_provenance`).
        """
        scale, unit = (1.0, "m") if self.dt is None else (1.0 / self.dt, "m s-1")
        names = {"u": "x", "v": "y", "w": "z"}
        ds = {"/x": self.x, "/y": self.y, "/z": self.z}
        units = {"/x": "m", "/y": "m", "/z": "m"}
        for name, (dtype, u, _) in QUALITY.items():
            ds[f"/{name}"] = np.asarray(self._quality()[name]).astype(dtype)
            units[f"/{name}"] = u
        for comp in "uvw":
            ds[f"/{comp}"] = (getattr(self, comp) * scale).astype(np.float32)
            units[f"/{comp}"] = unit
            ds[f"/{comp}_uncertainty"] = (getattr(self, f"{comp}_uncertainty")
                                          * scale).astype(np.float32)
            units[f"/{comp}_uncertainty"] = unit
        attrs = {"dt_s": np.nan if self.dt is None else self.dt,
                 "quantity": "displacement" if self.dt is None else "velocity",
                 "n_replaced": self.n_replaced, "Conventions": "CF-1.8",
                 "uncertainty_method": self.uncertainty_method,
                 **self._grid_attrs(), **(extra_attrs or {})}
        # the .vti first, then the HDF5 file: its `complete` mark (extra_attrs) is the last
        # thing written, inside its temporary, so a failed write leaves nothing marked
        check_writable(ds, path, "vectors", may_be_nan=NAN_DATASETS, may_be_inf=INF_DATASETS)
        vti = self.save_vtk(Path(path).with_suffix("")) if vtk else None
        p = write_h5(path, ds, attrs=attrs, units=units, config=config, kind="vectors",
                     may_be_nan=NAN_DATASETS, may_be_inf=INF_DATASETS,
                     finalize=lambda fh: _cf_dimensions(fh, names), provenance=provenance)
        return [p] if vti is None else [p, vti]

    def _grid_attrs(self) -> dict:
        """The attributes of :attr:`grid` and :attr:`window_vox` (:data:`GRID_ATTRS`)."""
        out = {}
        if self.grid is not None:
            out.update(voxel_m=np.array(self.grid.voxel, float),
                       volume_origin_m=np.array(self.grid.origin, float),
                       volume_shape=np.array(self.grid.shape, np.int64))
        if self.window_vox is not None:
            out["window_vox"] = np.array(self.window_vox, np.int64)
        return out

    def save_vtk(self, stem: Path) -> Path:
        """Write ``stem.vti`` (ParaView image data) atomically and return its path.

        It holds the vector field, its components' uncertainties and the per-vector quality
        (same names as in the HDF5 product).
        """
        from pyevtk.hl import imageToVTK
        def spacing(a):
            return float(a[1] - a[0]) if len(a) > 1 else 1.0

        def point(a):   # VTK point data is x-fastest: transpose [z, y, x] -> [x, y, z]
            return np.ascontiguousarray(np.asarray(a, np.float64).transpose(2, 1, 0))

        origin = (float(self.x[0]), float(self.y[0]), float(self.z[0]))
        sp = (spacing(self.x), spacing(self.y), spacing(self.z))
        scale = 1.0 if self.dt is None else 1.0 / self.dt
        data = {"displacement" if self.dt is None else "velocity": tuple(
            point(getattr(self, c) * scale) for c in "uvw")}
        for c in "uvw":
            data[f"{c}_uncertainty"] = point(getattr(self, f"{c}_uncertainty") * scale)
        for name, value in self._quality().items():
            if name != "snr":
                data[name] = point(np.asarray(value, np.float64))
        final = Path(str(stem) + ".vti")
        with atomic_path(final) as tmp:
            # pyevtk appends ".vti": it writes TMP.vti, which atomic_path removes on failure
            written = imageToVTK(str(tmp), origin=origin, spacing=sp, pointData=data)
            Path(written).replace(tmp)
        return final


#: Root attributes of the vectors product that hold :attr:`VectorResult.grid` (``voxel_m``
#: (dx, dy, dz), ``volume_origin_m`` (x, y, z of the centre of voxel [0, 0, 0]),
#: ``volume_shape`` (nz, ny, nx); metres, depth corrected) and :attr:`VectorResult.window_vox`
#: (``window_vox``, (wz, wy, wx) voxels).
GRID_ATTRS = ("voxel_m", "volume_origin_m", "volume_shape", "window_vox")


def physical_grid(grid: VolumeGrid, correction: DepthCorrection) -> VolumeGrid:
    """The effective ``grid`` with its depth (origin and voxel) corrected by ``correction``."""
    s = correction.scale
    return VolumeGrid((grid.origin[0], grid.origin[1], float(grid.origin[2] * s)),
                      (grid.voxel[0], grid.voxel[1], float(grid.voxel[2] * s)), grid.shape)


#: Datasets of the vectors product that may hold NaN (a rejected vector left unreplaced, a
#: masked window, an uncertainty or peak height not known); every other one is finite.
NAN_DATASETS = ("/u", "/v", "/w", "/u_uncertainty", "/v_uncertainty", "/w_uncertainty",
                "/peak_height", "/peak_ratio", "/snr")
#: Datasets that may hold +inf (a correlation peak without a second peak).
INF_DATASETS = ("/peak_ratio", "/snr")


def load_vectors(path: str | Path) -> VectorResult:
    """Read a vectors product (:meth:`VectorResult.save`) as a VectorResult of displacements.

    Velocity products (``dt_s`` set) are turned back into displacements (metres), ``dt`` kept.
    The grid and window (:data:`GRID_ATTRS`) come from the product's attributes, or, in a
    product written without them, from the ``[volume]`` and ``[piv] windows`` of its config
    (effective depth, as the experiment gave it); None where neither holds them. Every array
    is checked: NaN only in :data:`NAN_DATASETS`, inf only in :data:`INF_DATASETS`.
    """
    with open_product(path, "vectors", ReconstructionError) as fh:
        dt = fh.number("dt_s", allow_nan=True)
        f = 1.0 if not np.isfinite(dt) else dt
        names = ["x", "y", "z", "u", "v", "w", "valid", "snr", "peak_ratio", "peak_height",
                 "flag", "replaced", "u_uncertainty", "v_uncertainty", "w_uncertainty"]
        arrays = {k: fh.array(f"/{k}", allow_nan=f"/{k}" in NAN_DATASETS,
                              allow_inf=f"/{k}" in INF_DATASETS)
                  for k in names if f"/{k}" in fh}
        for name in ("voxel_m", "volume_origin_m"):
            if name in fh.attrs:
                fh.number(name)
        grid, window = _stored_grid(dict(fh.attrs))
        method = str(fh.attrs.get("uncertainty_method", "correlation"))
        n_replaced = int(fh.attrs.get("n_replaced", 0))
    optional = {k: arrays[k] for k in ("peak_height", "flag", "replaced") if k in arrays}
    optional.update({k: arrays[k].astype(float) * f for k in
                     ("u_uncertainty", "v_uncertainty", "w_uncertainty") if k in arrays})
    if "replaced" in optional:
        optional["replaced"] = optional["replaced"].astype(bool)
    return VectorResult(arrays["x"], arrays["y"], arrays["z"],
                        arrays["u"].astype(float) * f, arrays["v"].astype(float) * f,
                        arrays["w"].astype(float) * f, arrays["valid"].astype(bool),
                        arrays["snr"].astype(float), dt if np.isfinite(dt) else None,
                        n_replaced, grid=grid, window_vox=window, uncertainty_method=method,
                        **optional)


def _stored_grid(attrs: dict) -> tuple[VolumeGrid | None, tuple | None]:
    """``(grid, window_vox)`` of a vectors product's root attributes (see :func:`load_vectors`)."""
    import json

    from plenopiv.camera.grid import volume_from_dict
    from plenopiv.errors import ConfigError

    grid = window = None
    if all(k in attrs for k in ("voxel_m", "volume_origin_m", "volume_shape")):
        grid = VolumeGrid(tuple(float(v) for v in attrs["volume_origin_m"]),
                          tuple(float(v) for v in attrs["voxel_m"]),
                          tuple(int(n) for n in attrs["volume_shape"]))
    if "window_vox" in attrs:
        window = tuple(int(n) for n in attrs["window_vox"])
    if grid is not None and window is not None:
        return grid, window
    try:
        config = json.loads(attrs.get("config", "{}"))
    except (TypeError, ValueError):
        return grid, window
    if grid is None and isinstance(config.get("volume"), dict):
        try:
            grid = volume_from_dict(config["volume"])
        except ConfigError:
            grid = None
    windows = (config.get("piv") or {}).get("windows") if isinstance(config, dict) else None
    if window is None and windows:
        window = tuple(int(n) for n in windows[-1])
    return grid, window


def _cf_dimensions(fh, names) -> None:
    """Attach the 1-D coordinates of an open vectors file as HDF5 dimension scales.

    xarray and netCDF readers then see ``x``, ``y``, ``z`` as the coordinates.
    """
    cf_axes(fh)
    for name in ("u", "v", "w", *(f"{c}_uncertainty" for c in "uvw"), *QUALITY):
        for dim, axis in enumerate(("z", "y", "x")):
            fh[name].dims[dim].attach_scale(fh[axis])
    for comp, axis in names.items():
        fh[comp].attrs["long_name"] = f"{fh.attrs['quantity']} along {axis}"
        fh[f"{comp}_uncertainty"].attrs["long_name"] = (
            f"standard uncertainty of the {fh.attrs['quantity']} along {axis}")
    for name, (_, _, long_name) in QUALITY.items():
        fh[name].attrs["long_name"] = long_name
