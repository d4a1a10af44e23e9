"""Masks: sensor pixels the reconstruction ignores, voxels outside the flow that the PIV skips.

An image mask is a boolean ``(rows, cols)`` array, True for a pixel to ignore (a reflection,
a model in the view); :func:`plenopiv.workflow.volume.reconstruct_volume` drops those pixels' rows
of the system instead of taking them as dark. A volume mask is a boolean ``[z, y, x]`` array
on the reconstruction grid, True for a voxel outside the flow; :func:`plenopiv.piv.
correlate_volumes` zeroes those voxels and returns NaN, flagged vectors whose window centre
is masked. Both come from the ``[mask]`` table of an experiment
(:class:`plenopiv.config.experiment.MaskConfig`): files, and boxes and cylinders in volume
coordinates (the ``[volume]`` grid's, in mm).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from plenopiv.camera.grid import VolumeGrid
from plenopiv.errors import ConfigError

__all__ = ["box_mask", "cylinder_mask", "image_mask", "read_mask", "volume_mask"]


def read_mask(spec: str | Path, *, name: str = "mask") -> np.ndarray:
    """Read a boolean array from a file; non-zero values are True.

    ``spec`` is a ``.npy`` file, ``file.h5:/dataset`` (or a ``.h5`` file holding ``/mask``) or
    an image (TIFF, PNG).

    Raises
    ------
    ConfigError
        When the file is missing, unreadable or not numeric.
    """
    from plenopiv.products.files import check_input_file, split_dataset_spec
    from plenopiv.products.images import read_image

    path, dataset = split_dataset_spec(spec)
    check_input_file(path, name, ConfigError)
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            arr = np.load(path, allow_pickle=False)
        elif suffix in (".h5", ".hdf5"):
            import h5py

            with h5py.File(path, "r") as fh:
                key = dataset or "/mask"
                if key not in fh:
                    raise ConfigError(f"{name} file {str(path)!r} has no dataset {key!r}; "
                                      f"name it as {path}:/DATASET")
                arr = fh[key][()]
        else:
            arr = read_image(spec)
    except ConfigError:
        raise
    except Exception as exc:  # noqa: BLE001 - any reader failure is a bad mask file
        raise ConfigError(f"{name} file {str(path)!r} cannot be read: "
                          f"{type(exc).__name__}: {exc}") from None
    arr = np.asarray(arr)
    if not (arr.dtype == bool or np.issubdtype(arr.dtype, np.number)):
        raise ConfigError(f"{name} {str(spec)!r} has dtype {arr.dtype}: expected a boolean or "
                          "numeric array (non-zero = masked)")
    return arr != 0


def image_mask(cfg, shape, base_dir: Path = Path(".")) -> np.ndarray | None:
    """The ``[mask] image`` as a ``(rows, cols)`` bool array (None without one).

    ``shape``: the sensor's ``(rows, cols)``.
    """
    if cfg is None or cfg.image is None:
        return None
    p = Path(cfg.image)
    m = read_mask(p if p.is_absolute() else base_dir / p, name="[mask] image")
    if m.shape != tuple(shape):
        raise ConfigError(f"[mask] image {cfg.image!r} is {m.shape[0] if m.ndim else 0} x "
                          f"{m.shape[1] if m.ndim > 1 else 0} pixels; expected the sensor's "
                          f"{shape[0]} x {shape[1]} (rows x cols)")
    return m


def box_mask(grid: VolumeGrid, x, y, z, *, inside: bool = True) -> np.ndarray:
    """Voxels whose centre lies in the box ``x = (lo, hi)``, ``y``, ``z``: bool ``[z, y, x]``.

    The box is in metres, the grid's coordinates; ``inside=False`` returns the complement.
    """
    zz, yy, xx = np.meshgrid(grid.z, grid.y, grid.x, indexing="ij")
    m = ((xx >= min(x)) & (xx <= max(x)) & (yy >= min(y)) & (yy <= max(y))
         & (zz >= min(z)) & (zz <= max(z)))
    return m if inside else ~m


def cylinder_mask(grid: VolumeGrid, axis: str, centre, radius: float, length=None, *,
                  inside: bool = True) -> np.ndarray:
    """Voxels whose centre lies in a circular cylinder along ``axis`` ("x", "y" or "z").

    ``centre``: the axis's position in the two other coordinates (x, y, z order), metres;
    ``radius`` metres; ``length``: ``(lo, hi)`` along the axis, metres, or None (unbounded).
    ``inside=False`` returns the complement. Bool ``[z, y, x]``.
    """
    if axis not in ("x", "y", "z"):
        raise ConfigError(f"[[mask.cylinder]] axis = {axis!r}: expected 'x', 'y' or 'z'")
    zz, yy, xx = np.meshgrid(grid.z, grid.y, grid.x, indexing="ij")
    coords = {"x": xx, "y": yy, "z": zz}
    across = [coords[a] for a in "xyz" if a != axis]
    r2 = (across[0] - centre[0]) ** 2 + (across[1] - centre[1]) ** 2
    m = r2 <= radius**2
    if length is not None:
        along = coords[axis]
        m &= (along >= min(length)) & (along <= max(length))
    return m if inside else ~m


def volume_mask(cfg, grid: VolumeGrid, base_dir: Path = Path(".")) -> np.ndarray | None:
    """The ``[mask]`` volume mask on ``grid``: bool ``[z, y, x]``, None when nothing is masked.

    It is the ``volume`` array or'ed with every box and cylinder.
    """
    if cfg is None:
        return None
    out = np.zeros(grid.shape, dtype=bool)
    if cfg.volume is not None:
        p = Path(cfg.volume)
        arr = read_mask(p if p.is_absolute() else base_dir / p, name="[mask] volume")
        if arr.shape != tuple(grid.shape):
            raise ConfigError(f"[mask] volume {cfg.volume!r} has shape {list(arr.shape)}; "
                              f"expected the [volume] grid's [nz, ny, nx] = {list(grid.shape)}")
        out |= arr
    mm = 1e-3
    for b in cfg.box:
        out |= box_mask(grid, np.array(b.x_mm) * mm, np.array(b.y_mm) * mm,
                        np.array(b.z_mm) * mm, inside=b.masked == "inside")
    for c in cfg.cylinder:
        length = None if c.length_mm is None else np.array(c.length_mm) * mm
        out |= cylinder_mask(grid, c.axis, np.array(c.centre_mm) * mm, c.radius_mm * mm, length,
                             inside=c.masked == "inside")
    return out if out.any() else None
