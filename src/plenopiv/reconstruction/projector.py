"""The projector interface: the linear map W from a voxel volume to a sensor image.

``I_i = sum_j w_ij E_j`` (forward, I = W·E) and ``r_j = sum_i w_ij I_i`` (back, r = Wᵀ·I),
with E flattened in ``[z, y, x]`` and I in ``(row, col)`` C order. :class:`Projector` is the
protocol MLOS and SMART need; :class:`RowAccessProjector` adds the rows that row-action and
block MART walk; :class:`SparseProjector` is the explicit implementation, W in CSR form
(8 bytes per non-zero), whose row-scaled and row-selected views share the one CSR, with no
transposed copy (the back projection scatters into one accumulator per thread) and a
:class:`RowSchedule` for the parallel MART updates.

See docs/methods.md#projectors.
"""

from __future__ import annotations

import functools
import hashlib
import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numba
import numpy as np

from plenopiv.errors import ReconstructionError
from plenopiv.reconstruction._kernels import projector as _k

__all__ = ["CachedSums", "Projector", "RowAccessProjector", "RowSchedule", "SparseProjector"]


@runtime_checkable
class Projector(Protocol):
    """What a reconstruction needs from W (rows = pixels, columns = voxels).

    Volumes and images are 1-D: the volume flattened in ``[z, y, x]`` C order, the image in
    ``(row, col)`` C order. Intensities are in the sensor's counts (any consistent unit);
    weights are dimensionless beam-energy fractions, ``w_ij >= 0``.
    """

    @property
    def n_pixels(self) -> int:
        """Number of pixels (rows of W)."""
        ...

    @property
    def n_voxels(self) -> int:
        """Number of voxels (columns of W)."""
        ...

    def forward(self, volume: np.ndarray, *, out: np.ndarray | None = None) -> np.ndarray:
        """Return ``W·volume``, shape (n_pixels,), float32; written into ``out`` if given."""
        ...

    def back(self, image: np.ndarray, *, out: np.ndarray | None = None) -> np.ndarray:
        """Return ``Wᵀ·image``, shape (n_voxels,), float32; written into ``out`` if given."""
        ...

    def row_sums(self) -> np.ndarray:
        """Return ``sum_j w_ij`` per pixel, shape (n_pixels,)."""
        ...

    def column_sums(self) -> np.ndarray:
        """Return ``sum_i w_ij`` per voxel, shape (n_voxels,)."""
        ...


@runtime_checkable
class RowAccessProjector(Projector, Protocol):
    """A :class:`Projector` whose rows can be walked: W's CSR arrays and row schedules."""

    @property
    def indptr(self) -> np.ndarray:
        """CSR row pointers, int32 or int64, shape (n_pixels + 1,)."""
        ...

    @property
    def indices(self) -> np.ndarray:
        """CSR voxel indices, int32, shape (nnz,)."""
        ...

    @property
    def data(self) -> np.ndarray:
        """CSR weights, float32, shape (nnz,)."""
        ...

    @property
    def row_index(self) -> np.ndarray:
        """CSR row of each pixel, int64 (empty: pixel i is CSR row i)."""
        ...

    @property
    def row_scale(self) -> np.ndarray:
        """Scale of each pixel's CSR row, float32 (empty: 1)."""
        ...

    def row_schedule(self, *, chunk_rows: int = 16) -> RowSchedule:
        """All rows in voxel-disjoint groups of chunks (see :class:`RowSchedule`)."""
        ...

    def block_schedule(self, labels: np.ndarray, *, chunk_rows: int = 16) -> RowSchedule:
        """Rows cut into blocks by label, each block into voxel-disjoint groups of chunks."""
        ...


@dataclass(frozen=True, eq=False)
class RowSchedule:
    """The rows of W in blocks, groups and chunks, so that scatters can run in parallel.

    Block b (the pixels labelled ``labels[b]``, blocks in ascending label order) is the
    groups ``block_group_ptr[b]:block_group_ptr[b + 1]``; group g is the chunks
    ``group_ptr[g]:group_ptr[g + 1]``; chunk c is the rows
    ``rows[chunk_ptr[c]:chunk_ptr[c + 1]]``, consecutive rows of its block (ascending pixel
    index). No two chunks of one group share a voxel, so the chunks of a group may write
    their voxels in parallel (each chunk's rows one after another, by one thread) while the
    groups run in turn. A schedule of all rows has one block.

    Attributes
    ----------
    rows : ndarray of int64, shape (n_rows,)
    chunk_ptr : ndarray of int64, shape (n_chunks + 1,)
    group_ptr : ndarray of int64, shape (n_groups + 1,)
    block_group_ptr : ndarray of int64, shape (n_blocks + 1,)
    labels : ndarray, shape (n_blocks,)
    block_column_sums : ndarray of float32, shape (nnz,) or None
        For CSR entry p in a row of block B: ``sum_{i in B} w_{i, j}`` with ``j`` the entry's
        voxel, i.e. how much weight the whole block puts on that voxel (dimensionless).
    """

    rows: np.ndarray
    chunk_ptr: np.ndarray
    group_ptr: np.ndarray
    block_group_ptr: np.ndarray
    labels: np.ndarray
    block_column_sums: np.ndarray | None = None

    @property
    def n_groups(self) -> int:
        """Number of groups (colours summed over the blocks)."""
        return int(self.group_ptr.shape[0] - 1)

    @property
    def n_blocks(self) -> int:
        """Number of blocks."""
        return int(self.block_group_ptr.shape[0] - 1)

    @property
    def nbytes(self) -> int:
        """Memory held by the arrays, bytes."""
        arrays = (self.rows, self.chunk_ptr, self.group_ptr, self.block_group_ptr, self.labels,
                  self.block_column_sums)
        return int(sum(a.nbytes for a in arrays if a is not None))


class CachedSums:
    """``row_sums`` and ``column_sums`` of a projector from its ``forward`` and ``back``.

    Each is computed on first use (a projector is immutable; its row views are new objects).
    """

    @functools.cached_property
    def _row_sums(self) -> np.ndarray:
        return self.forward(np.ones(self.n_voxels, np.float32))

    @functools.cached_property
    def _column_sums(self) -> np.ndarray:
        return self.back(np.ones(self.n_pixels, np.float32))

    def row_sums(self) -> np.ndarray:
        """``sum_j w_ij`` per pixel (float32, shape (n_pixels,)); computed once and cached."""
        return self._row_sums

    def column_sums(self) -> np.ndarray:
        """``sum_i w_ij`` per voxel (float32, shape (n_voxels,)); computed once and cached."""
        return self._column_sums

    def set_column_sums(self, sums: np.ndarray) -> None:
        """Take ``sums`` as :meth:`column_sums`, computed elsewhere for the same rows.

        For a view that an earlier, equal view has already summed (the caller vouches for
        the equality); the array is kept as given (read-only use).
        """
        sums = np.asarray(sums)
        if sums.shape != (self.n_voxels,):
            raise ReconstructionError(f"column sums have shape {sums.shape}: expected "
                                      f"({self.n_voxels},)")
        self.__dict__["_column_sums"] = sums


class SparseProjector(CachedSums):
    """W as an explicit CSR matrix: rows = pixels, columns = voxels.

    Parameters
    ----------
    indptr : array_like of int, shape (n_pixels + 1,)
        CSR row pointers (int32 or int64; other integer types are converted to int64).
    indices : array_like of int, shape (nnz,)
        Voxel index of each non-zero, ``0 <= indices < n_voxels`` (stored as int32).
    data : array_like of float, shape (nnz,)
        Weight of each non-zero, the dimensionless fraction of the pixel's beam energy that
        crosses the voxel, finite and ``>= 0`` (stored as float32).
    n_voxels : int
        Number of voxels (columns), keyword-only.
    check : bool, optional
        Check the row pointers, the index range and the weights (one pass over the
        non-zeros). Default True.
    transpose : bool, optional
        Keep a transposed copy of W (built on the first ``back``) and back-project by a
        gather per voxel: faster than the default scatter (``benchmarks/bench_mart.py`` times
        both), for 8 bytes per non-zero more (the matrix's memory doubles). Default False.

    Notes
    -----
    ``forward`` gathers one row per pixel in parallel (numba ``prange``). ``back`` scatters
    without a transposed copy: the rows are cut into one chunk per numba thread, of about
    equal non-zeros, each scattering into its own float64 accumulator of n_voxels values,
    which are then summed per voxel; pixels of value zero are skipped. The scratch,
    ``n_threads * n_voxels * 8`` bytes, is kept between calls; with a pixel's beam crossing
    every depth slice (hundreds of non-zeros per voxel) it is a small fraction of the matrix.
    ``transpose=True`` trades memory for speed instead (see above);
    ``benchmarks/bench_mart.py`` times both, and a scatter that follows :meth:`row_schedule`.
    Duplicate (pixel, voxel) entries are summed, as in scipy.sparse.

    Examples
    --------
    >>> import numpy as np
    >>> W = SparseProjector(np.array([0, 2, 3]), np.array([0, 1, 1]),
    ...                     np.array([0.5, 0.5, 1.0]), n_voxels=2)
    >>> W.forward(np.array([2.0, 4.0]))
    array([3., 4.], dtype=float32)
    """

    def __init__(self, indptr, indices, data, *, n_voxels: int, check: bool = True,
                 transpose: bool = False):
        indptr = np.asarray(indptr)
        indices = np.asarray(indices)
        data = np.asarray(data)
        if indptr.ndim != 1 or indptr.shape[0] < 1 or not np.issubdtype(indptr.dtype, np.integer):
            raise ReconstructionError(
                f"indptr must be a 1-D integer array of length n_pixels + 1; got dtype "
                f"{indptr.dtype}, shape {indptr.shape}"
            )
        if indptr.dtype not in (np.int32, np.int64):
            indptr = indptr.astype(np.int64)
        if indices.ndim != 1 or not np.issubdtype(indices.dtype, np.integer):
            raise ReconstructionError(
                f"indices must be a 1-D integer array; got dtype {indices.dtype}, "
                f"shape {indices.shape}"
            )
        if data.ndim != 1 or data.shape != indices.shape:
            raise ReconstructionError(
                f"data must be 1-D with the length of indices ({indices.shape[0]}); got shape "
                f"{data.shape}"
            )
        n_voxels = int(n_voxels)
        if n_voxels < 1 or n_voxels > np.iinfo(np.int32).max:
            raise ReconstructionError(f"n_voxels must be in [1, 2**31 - 1]; got {n_voxels}")
        nnz = indices.shape[0]
        if indptr[0] != 0 or indptr[-1] != nnz:
            raise ReconstructionError(
                f"indptr must start at 0 and end at nnz = {nnz}; got {indptr[0]} ... "
                f"{indptr[-1]}"
            )
        if check:
            if np.any(np.diff(indptr) < 0):
                raise ReconstructionError("indptr must be non-decreasing")
            if nnz and (indices.min() < 0 or indices.max() >= n_voxels):
                raise ReconstructionError(
                    f"voxel indices must lie in [0, {n_voxels}); got [{indices.min()}, "
                    f"{indices.max()}]"
                )
            finite = np.isfinite(data)
            if nnz and not (finite.all() and data.min() >= 0):
                low = float(data[finite].min()) if finite.any() else float("nan")
                raise ReconstructionError(
                    "weights must be finite and >= 0 (beam-energy fractions); got "
                    f"{np.count_nonzero(~finite)} non-finite, smallest finite {low:g}"
                )
        self._indptr = np.ascontiguousarray(indptr)
        self._indices = np.ascontiguousarray(indices, dtype=np.int32)
        self._data = np.ascontiguousarray(data, dtype=np.float32)
        self._n_voxels = n_voxels
        self._row_index: np.ndarray | None = None   # None: row i is CSR row i
        self._row_scale: np.ndarray | None = None   # None: every row scaled by 1
        self._transpose = bool(transpose)
        self._transposed: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._scratch: np.ndarray | None = None
        self._bounds: np.ndarray | None = None
        self._schedule: tuple[str, RowSchedule] | None = None
        self._blocks: tuple[str, RowSchedule] | None = None

    # -- construction helpers -------------------------------------------------------------
    @classmethod
    def from_scipy(cls, matrix, *, check: bool = True, transpose: bool = False
                   ) -> SparseProjector:
        """Build from any scipy.sparse matrix or array of shape (n_pixels, n_voxels)."""
        csr = matrix.tocsr()
        return cls(csr.indptr, csr.indices, csr.data, n_voxels=csr.shape[1], check=check,
                   transpose=transpose)

    def to_scipy(self):
        """Return W as a ``scipy.sparse.csr_array``.

        It shares this projector's arrays, except for a row view (scaled or selected rows),
        whose rows are copied out.
        """
        import scipy.sparse

        if self.is_view:
            counts = np.diff(self._indptr)[self._rows()]
            indptr = np.zeros(self.n_pixels + 1, np.int64)
            np.cumsum(counts, out=indptr[1:])
            take = _row_entries(self._indptr, self._rows(), indptr)
            data = self._data[take] * np.repeat(self._scales(), counts)
            return scipy.sparse.csr_array((data.astype(np.float32), self._indices[take], indptr),
                                          shape=(self.n_pixels, self.n_voxels))
        return scipy.sparse.csr_array(
            (self._data, self._indices, self._indptr), shape=(self.n_pixels, self.n_voxels)
        )

    # -- the Projector protocol ----------------------------------------------------------
    @property
    def n_pixels(self) -> int:
        """Number of pixels (rows of W)."""
        if self._row_index is not None:
            return int(self._row_index.shape[0])
        return int(self._indptr.shape[0] - 1)

    @property
    def n_voxels(self) -> int:
        """Number of voxels (columns of W)."""
        return self._n_voxels

    @property
    def nnz(self) -> int:
        """Number of stored weights (of the whole CSR, which a row view shares)."""
        return int(self._indices.shape[0])

    @property
    def is_view(self) -> bool:
        """True for a row view (scaled or selected rows of a CSR held elsewhere)."""
        return self._row_index is not None or self._row_scale is not None

    @property
    def row_index(self) -> np.ndarray:
        """CSR row of each pixel, int64; empty when pixel i is CSR row i."""
        return _EMPTY_INDEX if self._row_index is None else self._row_index

    @property
    def row_scale(self) -> np.ndarray:
        """Factor of each pixel's CSR row, float32; empty when every factor is 1."""
        return _EMPTY_SCALE if self._row_scale is None else self._row_scale

    def _rows(self) -> np.ndarray:
        """CSR row of each pixel, int64 (materialised for the identity)."""
        if self._row_index is None:
            return np.arange(self.n_pixels, dtype=np.int64)
        return self._row_index

    def _scales(self) -> np.ndarray:
        """Factor of each pixel's row, float32 (materialised ones for no scaling)."""
        if self._row_scale is None:
            return np.ones(self.n_pixels, np.float32)
        return self._row_scale

    @property
    def shape(self) -> tuple[int, int]:
        """``(n_pixels, n_voxels)``."""
        return (self.n_pixels, self.n_voxels)

    @property
    def indptr(self) -> np.ndarray:
        """CSR row pointers (read them, do not write)."""
        return self._indptr

    @property
    def indices(self) -> np.ndarray:
        """CSR voxel indices, int32 (read them, do not write)."""
        return self._indices

    @property
    def data(self) -> np.ndarray:
        """CSR weights, float32 (read them, do not write)."""
        return self._data

    @property
    def nbytes(self) -> int:
        """Memory of W in bytes: CSR arrays, row view, any transposed copy.

        Not the scratch or the schedules; a view counts the CSR it shares.
        """
        arrays = ((self._indptr, self._indices, self._data, self.row_index, self.row_scale)
                  + (self._transposed or ()))
        return int(sum(a.nbytes for a in arrays))

    def forward(self, volume, *, out=None) -> np.ndarray:
        """Forward projection ``I = W·E``.

        Parameters
        ----------
        volume : array_like, shape (n_voxels,) or any shape of that size
            Voxel intensities E, flattened in ``[z, y, x]`` C order (converted to float32).
        out : ndarray of float32, shape (n_pixels,), optional
            Where to write the result.

        Returns
        -------
        ndarray of float32, shape (n_pixels,)
            Pixel intensities, summed in float64 and rounded once to float32.
        """
        x = _as_vector(volume, self.n_voxels, "volume", "n_voxels")
        if out is None:
            out = np.empty(self.n_pixels, np.float32)
        _k.forward_csr(self._indptr, self._indices, self._data, self.row_index, self.row_scale,
                       x, out)
        return out

    def back(self, image, *, out=None) -> np.ndarray:
        """Back projection ``r = Wᵀ·I``.

        Parameters
        ----------
        image : array_like, shape (n_pixels,) or any shape of that size
            Pixel values, flattened in ``(row, col)`` C order (converted to float32).
        out : ndarray of float32, shape (n_voxels,), optional
            Where to write the result.

        Returns
        -------
        ndarray of float32, shape (n_voxels,)
            Summed in float64 and rounded once to float32.
        """
        y = _as_vector(image, self.n_pixels, "image", "n_pixels")
        if out is None:
            out = np.empty(self.n_voxels, np.float32)
        if self._transpose:
            if self._transposed is None:
                self._transposed = _k.transpose_csr(self._indptr, self._indices, self._data,
                                                    self.row_index, self.row_scale,
                                                    self.n_pixels, self.n_voxels)
            _k.back_gather(*self._transposed, y, out)
            return out
        n_chunks = max(1, numba.get_num_threads())
        if self._scratch is None or self._scratch.shape[0] != n_chunks:
            self._scratch = np.empty((n_chunks, self.n_voxels), np.float64)
            ends = self._view_indptr()
            targets = np.linspace(0, ends[-1], n_chunks + 1).round().astype(np.int64)
            self._bounds = np.searchsorted(ends, targets).astype(np.int64)
            self._bounds[0], self._bounds[-1] = 0, self.n_pixels
        _k.back_scatter(self._indptr, self._indices, self._data, self.row_index,
                        self.row_scale, y, self._bounds, self._scratch, out)
        return out

    def _view_indptr(self) -> np.ndarray:
        """Cumulative non-zeros of the pixels (int64, n_pixels + 1): the view's row pointers."""
        if self._row_index is None:
            return self._indptr.astype(np.int64, copy=False)
        ends = np.zeros(self.n_pixels + 1, np.int64)
        np.cumsum(np.diff(self._indptr)[self._row_index], out=ends[1:])
        return ends

    def row_max(self) -> np.ndarray:
        """``max_j w_ij`` per pixel (float32, shape (n_pixels,); 0 for an empty row)."""
        counts = np.diff(self._indptr)
        out = np.zeros(counts.shape[0], np.float32)
        nonempty = counts > 0
        if nonempty.any():
            out[nonempty] = np.maximum.reduceat(self._data, self._indptr[:-1][nonempty])
        if self._row_index is not None:
            out = out[self._row_index]
        if self._row_scale is not None:
            out = (out * self._row_scale).astype(np.float32)
        return out

    def _view(self, row_index: np.ndarray | None, row_scale: np.ndarray | None
              ) -> SparseProjector:
        """A projector of rows ``row_index`` of this CSR scaled by ``row_scale`` (no copy)."""
        view = SparseProjector(self._indptr, self._indices, self._data, n_voxels=self.n_voxels,
                               check=False, transpose=self._transpose)
        view._row_index = row_index
        view._row_scale = row_scale
        return view

    def scale_rows(self, factors) -> SparseProjector:
        """W with row i multiplied by ``factors[i]``: a row view sharing this CSR.

        The factors are kept per row (float32, 4 bytes per row) and applied by the kernels as
        each weight is read, so W is not copied.
        """
        f = np.asarray(factors, np.float32).reshape(-1)
        if f.shape[0] != self.n_pixels:
            raise ReconstructionError(f"scale_rows: {f.shape[0]} factors for "
                                      f"{self.n_pixels} rows")
        scale = f if self._row_scale is None else (self._row_scale * f).astype(np.float32)
        return self._view(self._row_index, np.ascontiguousarray(scale))

    def select_rows(self, mask) -> SparseProjector:
        """The projector of the rows where ``mask`` (bool, n_pixels) is true: a row view.

        It shares this CSR and holds the selected rows' CSR indices (int64) and factors.
        """
        keep = np.asarray(mask, bool).reshape(-1)
        if keep.shape[0] != self.n_pixels:
            raise ReconstructionError(f"select_rows: a mask of {keep.shape[0]} values for "
                                      f"{self.n_pixels} rows")
        rows = np.flatnonzero(keep) if self._row_index is None else self._row_index[keep]
        scale = None if self._row_scale is None else self._row_scale[keep]
        return self._view(np.ascontiguousarray(rows, dtype=np.int64), scale)

    # -- row schedules -------------------------------------------------------------------
    def row_schedule(self, *, chunk_rows: int = 16) -> RowSchedule:
        """All rows in chunks of consecutive pixels, coloured so that a colour shares no voxel.

        Parameters
        ----------
        chunk_rows : int
            Pixels per chunk (>= 1). Larger chunks keep more locality and need fewer colours
            (barriers); smaller ones leave more chunks per colour to run in parallel.

        Returns
        -------
        RowSchedule
            One block; groups are the colours in ascending order, chunks ascending within a
            colour. Cached per ``chunk_rows`` (one entry). It depends on W alone, not on the
            number of threads, so a MART sweep that follows it gives the same volume on any
            machine.
        """
        chunk_rows = _positive_int(chunk_rows, "chunk_rows")
        key = f"all/{chunk_rows}"
        if self._schedule is None or self._schedule[0] != key:
            schedule = self._colour(np.array([0, self.n_pixels], np.int64),
                                    np.arange(self.n_pixels, dtype=np.int64),
                                    np.zeros(1, np.int64), chunk_rows, with_sums=False)
            self._schedule = (key, schedule)
        return self._schedule[1]

    def block_schedule(self, labels, *, chunk_rows: int = 16) -> RowSchedule:
        """Rows cut into blocks by label, each block into chunks coloured to share no voxel.

        Parameters
        ----------
        labels : array_like of int, shape (n_pixels,) or the image's shape
            Block label of each pixel (for example its perspective view, or the set of
            lenslets it lies under). Blocks are ordered by ascending label; within a block
            the pixels keep ascending index.
        chunk_rows : int
            Pixels per chunk (>= 1), see :meth:`row_schedule`.

        Returns
        -------
        RowSchedule
            With ``block_column_sums`` filled in. Cached: a second call with equal labels
            and ``chunk_rows`` returns the same object (one entry).
        """
        chunk_rows = _positive_int(chunk_rows, "chunk_rows")
        lab = np.asarray(labels)
        if lab.size != self.n_pixels or not np.issubdtype(lab.dtype, np.integer):
            raise ReconstructionError(
                f"block labels must be integers, one per pixel ({self.n_pixels}); got dtype "
                f"{lab.dtype}, {lab.size} values"
            )
        lab = np.ascontiguousarray(lab.reshape(-1), dtype=np.int64)
        key = f"{hashlib.sha1(lab.tobytes()).hexdigest()}/{chunk_rows}"
        if self._blocks is not None and self._blocks[0] == key:
            return self._blocks[1]
        unique, compact = np.unique(lab, return_inverse=True)
        block_rows = np.argsort(compact, kind="stable").astype(np.int64)
        block_ptr = np.zeros(unique.shape[0] + 1, np.int64)
        np.cumsum(np.bincount(compact, minlength=unique.shape[0]), out=block_ptr[1:])
        schedule = self._colour(block_ptr, block_rows, unique, chunk_rows, with_sums=True)
        self._blocks = (key, schedule)
        return schedule

    def _colour(self, block_ptr, block_rows, labels, chunk_rows, *, with_sums):
        """Colour the chunks of each block and order them by (block, colour, chunk)."""
        max_degree = _max_column_count(self._indices, self.n_voxels) if self.nnz else 1
        words = max(1, -(-max_degree // 64))
        while True:
            colour, n_colours, sums = _k.colour_chunks(
                self._indptr, self._indices, self._data, self.row_index, self.row_scale,
                block_ptr, block_rows, chunk_rows, self.n_voxels, words, with_sums)
            if n_colours.shape[0] == 0 or n_colours[0] >= 0:
                break
            words *= 2
        n_blocks = n_colours.shape[0]
        n_colours = np.maximum(n_colours, 1)  # an empty block keeps one (empty) group
        block_group_ptr = np.zeros(n_blocks + 1, np.int64)
        np.cumsum(n_colours, out=block_group_ptr[1:])
        # chunk k (numbered block by block) covers block_rows[chunk_start[k]:chunk_stop[k]]
        chunks_per_block = -(-np.diff(block_ptr) // chunk_rows)
        chunk_block = np.repeat(np.arange(n_blocks), chunks_per_block)
        first_chunk = np.cumsum(chunks_per_block) - chunks_per_block
        chunk_start = (block_ptr[:-1][chunk_block]
                       + (np.arange(chunk_block.shape[0]) - first_chunk[chunk_block])
                       * chunk_rows)
        chunk_stop = np.minimum(chunk_start + chunk_rows, block_ptr[1:][chunk_block])
        chunk_group = block_group_ptr[chunk_block] + colour
        order = np.argsort(chunk_group, kind="stable")
        lengths = (chunk_stop - chunk_start)[order]
        chunk_ptr = np.zeros(order.shape[0] + 1, np.int64)
        np.cumsum(lengths, out=chunk_ptr[1:])
        position = (np.repeat(chunk_start[order] - chunk_ptr[:-1], lengths)
                    + np.arange(chunk_ptr[-1]))
        n_groups = int(block_group_ptr[-1])
        group_ptr = np.zeros(n_groups + 1, np.int64)
        np.cumsum(np.bincount(chunk_group, minlength=n_groups), out=group_ptr[1:])
        return RowSchedule(block_rows[position], chunk_ptr, group_ptr, block_group_ptr, labels,
                           sums if with_sums else None)


_EMPTY_INDEX = np.zeros(0, np.int64)
_EMPTY_SCALE = np.zeros(0, np.float32)


def _max_column_count(indices: np.ndarray, n_voxels: int) -> int:
    """Largest number of non-zeros of one voxel (column) of the CSR.

    Counted by a kernel in one pass: no int64 copy of the indices, whole or in chunks, which
    would add to the peak memory of a reconstruction
    (``benchmarks/bench_weights.py --reconstruct`` traces it).
    """
    counts = np.zeros(n_voxels, np.int64)
    _k.column_counts(indices, counts)
    return int(counts.max())


def _row_entries(indptr: np.ndarray, rows: np.ndarray, view_indptr: np.ndarray) -> np.ndarray:
    """CSR entry positions of ``rows`` in order (int64, one per non-zero of the view)."""
    counts = np.diff(view_indptr)
    starts = np.repeat(indptr[:-1][rows].astype(np.int64) - view_indptr[:-1], counts)
    return starts + np.arange(view_indptr[-1], dtype=np.int64)


def _positive_int(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1; got {value!r}")
    return int(value)


def _as_vector(values, length: int, name: str, what: str) -> np.ndarray:
    """Flatten to a contiguous float32 vector of ``length``, or raise naming the mismatch."""
    a = np.asarray(values)
    if a.size != length:
        raise ReconstructionError(
            f"{name} has {a.size} values (shape {a.shape}); the projector expects "
            f"{what} = {length}"
        )
    return np.ascontiguousarray(a.reshape(-1), dtype=np.float32)


def _output_volume(out, shape) -> np.ndarray:
    """``out`` (contiguous float32, n_voxels values) as a ``shape`` view, or a new array."""
    if out is None:
        return np.empty(shape, np.float32)
    if out.dtype != np.float32 or out.size != math.prod(shape) or not out.flags.c_contiguous:
        raise ReconstructionError(f"back: out must be a contiguous float32 array of "
                                  f"{math.prod(shape)} values")
    return out.reshape(shape)
