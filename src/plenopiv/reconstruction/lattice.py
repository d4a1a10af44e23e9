"""A matrix-free projector for cameras with an axis-aligned square lenslet lattice.

:class:`LatticeProjector` computes the weights of :mod:`plenopiv.reconstruction.weights` on
the fly from two small tables: where the lattice rows and columns run along the sensor's, a
pixel's beam on every depth slice is the product of a profile along x that depends only on its
sensor column and one along y that depends only on its row. It implements the
:class:`~plenopiv.reconstruction.projector.Projector` protocol, enough for MLOS and SMART; it
traces a pixel cut by the aperture's edge through its cell centre and drops no small weights,
so it agrees with the explicit weights to float32 rounding when the light field is built with
``edge_centroid=False``.

See docs/methods.md#projectors.
"""

from __future__ import annotations

import contextlib
import math
import threading

import numpy as np

from plenopiv._threads import run_slices
from plenopiv.camera.grid import VolumeGrid
from plenopiv.errors import ReconstructionError
from plenopiv.lightfield import LightField
from plenopiv.reconstruction._kernels import lattice as _k
from plenopiv.reconstruction.geometry import SEPARABLE_TOLERANCE, separable_axes
from plenopiv.reconstruction.projector import CachedSums, _as_vector, _output_volume

__all__ = ["LatticeProjector", "separable_axes"]

#: Sensor rows per task of the forward contraction (they share the slices' rows in cache).
ROW_BLOCK = 16


def _transpose_rows(ys, yc, yw, ny) -> dict:
    """The row profiles by voxel row.

    For voxel row iy on slice k, the sensor rows that reach it and their weights are
    ``t_row``/``t_w[t_ptr[iy * nz + k]:t_ptr[iy * nz + k + 1]]``.
    """
    nz, nrow, kmax = yw.shape
    k, r, j = np.nonzero(np.arange(kmax)[None, None, :] < yc[:, :, None])
    key = (ys[k, r].astype(np.int64) + j) * nz + k
    order = np.argsort(key, kind="stable")
    ptr = np.searchsorted(key[order], np.arange(ny * nz + 1)).astype(np.int64)
    return {"t_ptr": ptr, "t_row": r[order].astype(np.int32),
            "t_w": np.ascontiguousarray(yw[k, r, j][order])}


class _Scratch:
    """The float32 projection buffer of a projector and its views.

    Inside :meth:`keeping` (a reconstruction's sweeps) one buffer serves call after call:
    allocated afresh for every projection it costs its page faults each time (0.76 GB a
    call at full size). Outside, and for a projection that finds it in use (another
    thread), each call takes its own, freed when it returns.
    """

    def __init__(self):
        self._lock = threading.Lock()
        self._array: np.ndarray | None = None
        self._keepers = 0

    @contextlib.contextmanager
    def keeping(self):
        with self._lock:
            self._keepers += 1
        try:
            yield
        finally:
            with self._lock:
                self._keepers -= 1
                if not self._keepers:
                    self._array = None

    @contextlib.contextmanager
    def buffer(self, shape):
        if not self._keepers or not self._lock.acquire(blocking=False):
            yield np.empty(shape, np.float32)
            return
        try:
            if self._array is None or self._array.shape != tuple(shape):
                self._array = None
                self._array = np.empty(shape, np.float32)
            yield self._array
        finally:
            self._lock.release()

    def __getstate__(self):
        return {}

    def __setstate__(self, state):
        self.__init__()


class LatticeProjector(CachedSums):
    """W for a lattice-aligned camera, never stored: see the module docstring.

    Build it with :meth:`from_light_field`. ``select_rows`` and ``scale_rows`` return cheap
    views that share the tables (a subset of the rays, or the rays scaled).

    Memory: the tables (2 × slices × (rows + cols) × ``kmax`` × 8 bytes), the rays (16 bytes
    each) and a float32 buffer of slices × voxel rows × used sensor columns, allocated per
    projection (757 MB for the Auburn camera and 200 slices).
    """

    def __init__(self, tables: dict, ray_row, ray_col, ray_scale, grid: VolumeGrid,
                 scratch: _Scratch | None = None):
        self._t = tables
        self._scratch = _Scratch() if scratch is None else scratch
        self._ray_row = np.ascontiguousarray(ray_row, np.int64)
        self._ray_col = np.ascontiguousarray(ray_col, np.int64)
        self._scale = np.ascontiguousarray(ray_scale, np.float32)
        if np.any(np.diff(self._ray_row) < 0):
            raise ReconstructionError("LatticeProjector rays must be sorted by sensor row")
        self.grid = grid
        n_rows = tables["ys"].shape[1]
        self._row_ptr = np.searchsorted(self._ray_row, np.arange(n_rows + 1)).astype(np.int64)
        self._row_used = np.diff(self._row_ptr) > 0

    # -- construction ----------------------------------------------------------------------
    @classmethod
    def from_light_field(cls, lf: LightField, grid: VolumeGrid, *,
                         tolerance: float = SEPARABLE_TOLERANCE) -> LatticeProjector:
        """The projector of ``lf``'s lit pixels onto ``grid``.

        Raises
        ------
        ReconstructionError
            The rays are not separable (a rotated or hexagonal lattice, or calibrated centres
            that scatter by more than ``tolerance`` of a cell or footprint).
        """
        axes = separable_axes(lf, tolerance=tolerance)
        if axes is None:
            raise ReconstructionError(
                "the matrix-free lattice projector needs an axis-aligned square lenslet "
                "lattice (rays whose x depends only on the sensor column and y only on the "
                "row); this calibration's lattice is rotated, hexagonal or irregular: use "
                "[reconstruction] projector = \"sparse\"")
        u_col, xf_col, u_row, xf_row = axes
        cols = lf.pixel % lf.shape[1]
        c0, c1 = int(cols.min()), int(cols.max()) + 1
        so = lf.object_distance
        t = np.ascontiguousarray((so + grid.z) / so, np.float64)
        a, b = lf.cell, lf.footprint
        al = np.abs(1.0 - t) * a
        be = t * b
        half = 0.5 * (al + be)
        area = math.pi * lf.aperture_radius ** 2
        vx, vy = float(grid.voxel[0]), float(grid.voxel[1])
        nz, ny, nx = grid.shape
        kmax = int(math.ceil(float((al + be).max()) / min(vx, vy))) + 2
        tables = {"c0": c0}
        for name, u, xf, origin, vox, n in (("x", u_col[c0:c1], xf_col[c0:c1], grid.origin[0],
                                             vx, nx),
                                            ("y", u_row, xf_row, grid.origin[1], vy, ny)):
            valid = np.isfinite(u) & np.isfinite(xf)
            u = np.where(valid, u, 0.0)
            xf = np.where(valid, xf, 0.0)
            start = np.zeros((nz, len(u)), np.int32)
            count = np.zeros((nz, len(u)), np.int32)
            w = np.zeros((nz, len(u), kmax), np.float32)
            worst = _k.axis_tables(u, xf, valid, t, al, be, half, float(origin), vox, n, kmax,
                                   start, count, w)
            if worst > kmax:    # cannot happen: kmax bounds the beam's width
                raise ReconstructionError(f"beam profile of {worst} voxels > table {kmax}")
            tables[name + "s"], tables[name + "c"], tables[name + "w"] = start, count, w
        # the per-slice factor (a β)² / (A Δx Δy) of the explicit weights goes with y
        tables["yw"] *= ((a * be) ** 2 / (area * vx * vy)).astype(np.float32)[:, None, None]
        tables.update(_transpose_rows(tables["ys"], tables["yc"], tables["yw"], ny))
        tables["col_max"] = np.ascontiguousarray(tables["xw"].max(axis=2).T)
        tables["row_max"] = np.ascontiguousarray(tables["yw"].max(axis=2).T)
        rows = lf.pixel // lf.shape[1]
        return cls(tables, rows, cols - c0, lf.lit, grid)

    # -- views -----------------------------------------------------------------------------
    def select_rows(self, mask) -> LatticeProjector:
        """The projector of the rays where ``mask`` (bool, n_pixels) is true."""
        mask = np.asarray(mask, bool)
        return LatticeProjector(self._t, self._ray_row[mask], self._ray_col[mask],
                                self._scale[mask], self.grid, self._scratch)

    def scale_rows(self, factors) -> LatticeProjector:
        """The projector with row i multiplied by ``factors[i]``."""
        return LatticeProjector(self._t, self._ray_row, self._ray_col,
                                self._scale * np.asarray(factors, np.float32), self.grid,
                                self._scratch)

    # -- the Projector protocol ------------------------------------------------------------
    @property
    def n_pixels(self) -> int:
        """Number of rays (rows of W)."""
        return int(self._ray_row.shape[0])

    @property
    def n_voxels(self) -> int:
        """Number of voxels (columns of W)."""
        return int(self.grid.n_voxels)

    @property
    def nbytes(self) -> int:
        """Memory of the tables and rays in bytes (not the per-call buffer)."""
        arrays = [v for v in self._t.values() if isinstance(v, np.ndarray)]
        arrays += [self._ray_row, self._ray_col, self._scale, self._row_ptr]
        return int(sum(x.nbytes for x in arrays))

    def reusing_buffers(self):
        """A context in which this projector and its views project through one buffer.

        A reconstruction's sweeps (:class:`_Scratch`).
        """
        return self._scratch.keeping()

    def _buffer(self):
        """The projection buffer (slices × voxel rows × sensor columns), as a context."""
        nz, ny, _ = self.grid.shape
        return self._scratch.buffer((nz, ny, self._t["xs"].shape[1]))

    def forward(self, volume, *, out=None) -> np.ndarray:
        """``I = W·E`` for E of n_voxels values (``[z, y, x]`` order); float32 (n_pixels,)."""
        e = _as_vector(volume, self.n_voxels, "volume", "n_voxels").reshape(self.grid.shape)
        t = self._t
        nz, ny, _ = self.grid.shape
        if out is None:
            out = np.empty(self.n_pixels, np.float32)
        with self._buffer() as tmp:
            run_slices(_k.contract_x, nz * ny, e, t["xs"], t["xc"], t["xw"], tmp)
            run_slices(_k.contract_y, _k.row_blocks(t["ys"].shape[1], ROW_BLOCK), tmp,
                       t["ys"], t["yc"], t["yw"], self._row_ptr, self._ray_col, self._scale,
                       ROW_BLOCK, out)
        return out

    def back(self, image, *, out=None) -> np.ndarray:
        """``r = Wᵀ·I`` for I of n_pixels values; float32 (n_voxels,)."""
        y = _as_vector(image, self.n_pixels, "image", "n_pixels")
        t = self._t
        n_rows, n_cols = t["ys"].shape[1], t["xs"].shape[1]
        dense = np.zeros((n_rows, n_cols), np.float32)
        dense[self._ray_row, self._ray_col] = y * self._scale
        used = self._row_used & dense.any(axis=1)
        nz, ny, _ = self.grid.shape
        vol = _output_volume(out, self.grid.shape)
        with self._buffer() as tmp:
            run_slices(_k.spread_y, ny, dense, used, t["t_ptr"], t["t_row"], t["t_w"], tmp)
            run_slices(_k.spread_x, nz * ny, tmp, t["xs"], t["xc"], t["xw"], vol)
        return vol.reshape(-1) if out is None else out

    def row_max(self) -> np.ndarray:
        """``max_j w_ij`` per ray (float32)."""
        t = self._t
        out = np.empty(self.n_pixels, np.float32)
        run_slices(_k.row_max, len(out), self._ray_row, self._ray_col, self._scale,
                   t["col_max"], t["row_max"], out)
        return out
