"""A matrix-free projector for any lenslet lattice: rotated, hexagonal, jittered.

Under one lenslet the rays share X_f, and a pixel's aperture position has its x fixed by the
pixel's column and its y by its row, whatever the lattice; so within each lenslet the weights
separate. :class:`LensletProjector` computes them on the fly, lenslet by lenslet and slice by
slice (:mod:`plenopiv.reconstruction._kernels.real_lattice`), from a few numbers per lenslet;
the calibrated centres and focal spots enter as they are. Like the lattice projector it
serves MLOS and SMART and agrees with the explicit weights to float32 rounding when the light
field is built with ``edge_centroid=False``. :func:`matrix_free_projector` picks the lattice or
the per-lenslet projector; :func:`estimate_lenslet_gb` estimates the memory.

See docs/methods.md#projectors.
"""

from __future__ import annotations

import functools
import hashlib
import math
import threading

import numba
import numpy as np

from plenopiv._threads import run_slices
from plenopiv.camera.grid import VolumeGrid
from plenopiv.errors import ReconstructionError
from plenopiv.lightfield import LightField
from plenopiv.reconstruction._kernels import real_lattice as _k
from plenopiv.reconstruction.projector import CachedSums, _as_vector, _output_volume

__all__ = ["LensletProjector", "compile_ahead", "estimate_lenslet_gb",
           "lenslet_weights_reference", "matrix_free_projector"]

#: Largest micro-image (rows or columns of one lenslet's lit pixels) the projector takes; the
#: Auburn camera's are 17 px, thesis-era cameras' 10-30 px.
MAX_MICRO_IMAGE_PX = 64


def _lenslet_tables(lf: LightField) -> dict:
    """Per-lenslet micro-image lines and the rays in lenslet order (see LensletProjector)."""
    if lf.n_rays == 0:
        raise ReconstructionError("the light field has no rays: no pixel of the camera is lit")
    cols_n = lf.shape[1]
    row = lf.pixel // cols_n
    col = lf.pixel % cols_n
    order = np.argsort(lf.lenslet, kind="stable")
    lens_ids, ray_lens = np.unique(lf.lenslet[order], return_inverse=True)
    n_lens = len(lens_ids)
    ray_ptr = np.searchsorted(ray_lens, np.arange(n_lens + 1)).astype(np.int64)
    r, c = row[order], col[order]
    r0 = np.minimum.reduceat(r, ray_ptr[:-1])
    c0 = np.minimum.reduceat(c, ray_ptr[:-1])
    n_row = (np.maximum.reduceat(r, ray_ptr[:-1]) - r0 + 1).astype(np.int64)
    n_col = (np.maximum.reduceat(c, ray_ptr[:-1]) - c0 + 1).astype(np.int64)
    box = int(max(n_row.max(), n_col.max()))
    if box > MAX_MICRO_IMAGE_PX:
        worst = int(np.argmax(np.maximum(n_row, n_col)))
        raise ReconstructionError(
            f"lenslet {int(lens_ids[worst])} spans {int(n_row[worst])} × {int(n_col[worst])} "
            f"pixels, more than the {MAX_MICRO_IMAGE_PX} px the matrix-free projector takes "
            "per micro-image: check the calibration's focal spots and f_number, or use "
            "[reconstruction] projector = \"sparse\" on a smaller volume")
    # the cell centre's aperture coordinate u = -(pixel - spot) · cell: the spot from the
    # fully lit rays (the others may carry the centroid shift of their lit part)
    u = lf.u[order]
    full = lf.lit[order] >= 1.0 - 1e-9
    spot = np.empty((n_lens, 2))
    for axis, line in ((0, c), (1, r)):
        est = line + u[:, axis] / lf.cell
        tot = np.add.reduceat(np.where(full, est, 0.0), ray_ptr[:-1])
        cnt = np.add.reduceat(full.astype(float), ray_ptr[:-1])
        mean_all = np.add.reduceat(est, ray_ptr[:-1]) / np.diff(ray_ptr)
        with np.errstate(invalid="ignore", divide="ignore"):
            spot[:, axis] = np.where(cnt > 0, tot / cnt, mean_all)
    offs = np.arange(box)
    u_col = -((c0[:, None] + offs[None, :]) - spot[:, 0:1]) * lf.cell
    u_row = -((r0[:, None] + offs[None, :]) - spot[:, 1:2]) * lf.cell
    xf = lf.focal_plane_position[order][ray_ptr[:-1]]
    return {"u_col": np.ascontiguousarray(u_col), "u_row": np.ascontiguousarray(u_row),
            "n_col": n_col, "n_row": n_row,
            "xf_x": np.ascontiguousarray(xf[:, 0]), "xf_y": np.ascontiguousarray(xf[:, 1]),
            "ray_lens": ray_lens.astype(np.int64),
            "ray_r": (r - r0[ray_lens]).astype(np.int64),
            "ray_c": (c - c0[ray_lens]).astype(np.int64),
            "ray_scale": lf.lit[order].astype(np.float32),
            "ray_pos": order.astype(np.int64)}


def _optics(lf: LightField) -> dict:
    """Return the light field's scalars that the slice tables need (metres)."""
    return {"object_distance": lf.object_distance, "cell": lf.cell,
            "footprint": lf.footprint, "aperture_radius": lf.aperture_radius}


def _slice_tables(lf: dict, grid: VolumeGrid) -> dict:
    """Per-slice beam parameters of ``grid``'s depth slices.

    t = (S_o + Z)/S_o, the box widths α = |1 - t| a and β = t b (metres), half the profile's
    support and the weight factor (a β)² / (A Δx Δy).
    """
    so = lf["object_distance"]
    t = np.ascontiguousarray((so + np.asarray(grid.z, float)) / so)
    al = np.abs(1.0 - t) * lf["cell"]
    be = t * lf["footprint"]
    area = math.pi * lf["aperture_radius"] ** 2
    vx, vy = float(grid.voxel[0]), float(grid.voxel[1])
    kmax = int(math.ceil(float((al + be).max()) / min(vx, vy))) + 2
    return {"t": t, "al": al, "be": be, "half": 0.5 * (al + be), "shape": _k.cdf_shapes(al, be),
            "factor": (lf["cell"] * be) ** 2 / (area * vx * vy), "kmax": kmax,
            "optics": lf}


def _ray_windows(ray_ptr, ray_r, ray_c) -> np.ndarray:
    """Return the rows ``[0]:[1]`` and columns ``[2]:[3]`` (local) of each lenslet's rays.

    A view of a few rays (the bright ones) then computes only their lines' profiles.
    """
    n_lens = len(ray_ptr) - 1
    window = np.zeros((n_lens, 4), np.int64)
    full = np.flatnonzero(np.diff(ray_ptr) > 0)
    if len(full):
        starts = ray_ptr[full]
        window[full, 0] = np.minimum.reduceat(ray_r, starts)
        window[full, 1] = np.maximum.reduceat(ray_r, starts) + 1
        window[full, 2] = np.minimum.reduceat(ray_c, starts)
        window[full, 3] = np.maximum.reduceat(ray_c, starts) + 1
    return window


class LensletProjector(CachedSums):
    """W for any lenslet lattice, never stored: see the module docstring.

    Build it with :meth:`from_light_field`; ``select_rows`` and ``scale_rows`` return views
    sharing the per-lenslet tables.
    """

    def __init__(self, lenses: dict, rays: dict, slices: dict, grid: VolumeGrid):
        self._lens = lenses
        self._rays = rays
        self._slices = slices
        self.grid = grid
        n_lens = len(lenses["xf_x"])
        self._ray_ptr = np.searchsorted(rays["ray_lens"], np.arange(n_lens + 1)).astype(np.int64)
        self._window = _ray_windows(self._ray_ptr, rays["ray_r"], rays["ray_c"])
        self._kept_view_sums = None   # (rows digest, column sums) of summed_row_view

    @classmethod
    def from_light_field(cls, lf: LightField, grid: VolumeGrid) -> LensletProjector:
        """Build the projector of ``lf``'s rays onto ``grid`` (any lattice).

        Raises
        ------
        ReconstructionError
            The light field is empty, or a micro-image spans more than
            :data:`MAX_MICRO_IMAGE_PX` pixels.
        """
        tables = _lenslet_tables(lf)
        ray_keys = ("ray_lens", "ray_r", "ray_c", "ray_scale", "ray_pos")
        rays = {k: tables.pop(k) for k in ray_keys}
        return cls(tables, rays, _slice_tables(_optics(lf), grid), grid)

    def on_grid(self, grid: VolumeGrid) -> LensletProjector:
        """Return the projector of the same rays (and row scales) onto another grid."""
        return LensletProjector(self._lens, self._rays,
                                _slice_tables(self._slices["optics"], grid), grid)

    # -- views -----------------------------------------------------------------------------
    def select_rows(self, mask) -> LensletProjector:
        """Return the projector of the rays where ``mask`` (bool, n_pixels) is true."""
        mask = np.asarray(mask, bool)
        if mask.shape != (self.n_pixels,):
            raise ReconstructionError(f"row mask has shape {mask.shape}: expected "
                                      f"({self.n_pixels},)")
        keep = mask[self._rays["ray_pos"]]
        new_pos = np.cumsum(mask) - 1
        rays = {k: v[keep] for k, v in self._rays.items()}
        rays["ray_pos"] = new_pos[rays["ray_pos"]].astype(np.int64)
        return LensletProjector(self._lens, rays, self._slices, self.grid)

    def summed_row_view(self, mask, *, column_sums=None) -> LensletProjector:
        """``select_rows(mask)`` with its column sums, kept on this projector for the next call.

        SMART with this projector takes rows that depend on the geometry and the image mask
        alone (:func:`plenopiv.reconstruction.solve.solve_volume`), so a series of images
        asks for the same view again: its column sums (one back projection) are computed
        once and kept here, one float32 volume (not the view's copies of the rays). A view
        of other rows replaces them. Two threads asking at once may both sum; the result is
        the same.

        ``column_sums`` (float32, n_voxels), when given and none are kept for these rows, are
        taken as the view's instead of a back projection: sums of exactly these rows' weights
        computed elsewhere (the line of sight pools them from its cells); the caller vouches.
        """
        mask = np.asarray(mask, bool)
        view = self.select_rows(mask)
        digest = hashlib.blake2b(np.packbits(mask).tobytes(), digest_size=16).digest()
        kept = self._kept_view_sums
        if kept is not None and kept[0] == digest:
            view.set_column_sums(kept[1])
        else:
            if column_sums is not None:
                view.set_column_sums(np.asarray(column_sums, np.float32))
            self._kept_view_sums = (digest, view.column_sums())
        return view

    def scale_rows(self, factors) -> LensletProjector:
        """Return the projector with row i multiplied by ``factors[i]``."""
        f = np.asarray(factors, np.float32)
        rays = dict(self._rays)
        rays["ray_scale"] = (rays["ray_scale"] * f[rays["ray_pos"]]).astype(np.float32)
        return LensletProjector(self._lens, rays, self._slices, self.grid)

    # -- the Projector protocol ------------------------------------------------------------
    @property
    def n_pixels(self) -> int:
        """Number of rays (rows of W)."""
        return int(self._rays["ray_pos"].shape[0])

    @property
    def n_voxels(self) -> int:
        """Number of voxels (columns of W)."""
        return int(self.grid.n_voxels)

    @property
    def nbytes(self) -> int:
        """Memory of the tables and rays in bytes (not the per-call buffers)."""
        arrays = (list(self._lens.values()) + list(self._rays.values())
                  + [self._ray_ptr, self._window])
        return int(sum(a.nbytes for a in arrays if isinstance(a, np.ndarray)))

    def _args(self) -> tuple:
        s, le, r = self._slices, self._lens, self._rays
        g = self.grid
        return ((s["t"], s["shape"], s["half"], s["factor"], float(g.origin[0]),
                 float(g.origin[1]), float(g.voxel[0]), float(g.voxel[1])),
                (le["u_col"], le["u_row"], self._window, le["xf_x"], le["xf_y"],
                 self._ray_ptr, r["ray_r"], r["ray_c"], r["ray_scale"], r["ray_pos"],
                 s["kmax"]))

    def forward(self, volume, *, out=None) -> np.ndarray:
        """``I = W·E`` for E of n_voxels values (``[z, y, x]`` order); float32 (n_pixels,)."""
        e = _as_vector(volume, self.n_voxels, "volume", "n_voxels").reshape(self.grid.shape)
        if out is None:
            out = np.empty(self.n_pixels, np.float32)
        slices, lenses = self._args()
        return _k.forward(e, *slices, *lenses, out)

    def back(self, image, *, out=None) -> np.ndarray:
        """``r = Wᵀ·I`` for I of n_pixels values; float32 (n_voxels,)."""
        y = _as_vector(image, self.n_pixels, "image", "n_pixels")
        slices, lenses = self._args()
        order = _k.interleaved_order(self.grid.shape[0], numba.get_num_threads())
        into = _output_volume(out, self.grid.shape)
        vol = _k.back(y, *slices, *lenses, into, order)
        return vol.reshape(-1) if out is None else out

    def _row_reduce(self, maximum: bool) -> np.ndarray:
        """Each ray's largest (``maximum``) or summed weight (float32, n_pixels)."""
        slices, lenses = self._args()
        nz, ny, nx = self.grid.shape
        out = np.zeros(self.n_pixels, np.float32)
        run_slices(_k.row_reduce, len(self._lens["xf_x"]), *slices, nx, ny, *lenses,
                   maximum, out)
        return out

    @functools.cached_property
    def _row_sums(self) -> np.ndarray:
        # the product of each slice's profile sums: a third of a forward projection of ones
        return self._row_reduce(False)

    def row_max(self) -> np.ndarray:
        """``max_j w_ij`` per ray (float32)."""
        return self._row_reduce(True)


def kernel_signatures() -> dict:
    """The numba signatures of the projector's kernels as :class:`LensletProjector` calls them.

    ``{kernel: argument types}`` for the row reduction, the back and the forward projection,
    from arrays of the dtypes and layouts that :meth:`LensletProjector._args` and the
    Projector protocol pass (a test holds them to a real projector's).
    """
    f64, f32, i64 = np.float64, np.float32, np.int64

    def v(dtype, ndim=1):
        return np.zeros((1,) * ndim, dtype)

    slices = (v(f64), v(f64, 2), v(f64), v(f64), 0.0, 0.0, 1.0, 1.0)
    lenses = (v(f64, 2), v(f64, 2), v(i64, 2), v(f64), v(f64), v(i64), v(i64), v(i64), v(f32),
              v(i64), 1)
    args = {_k.row_reduce: (*slices, 1, 1, *lenses, False, v(f32), 0, 1),
            _k.back: (v(f32), *slices, *lenses, v(f32, 3), v(i64)),
            _k.forward: (v(f32, 3), *slices, *lenses, v(f32))}
    return {kernel: tuple(numba.typeof(a) for a in a_) for kernel, a_ in args.items()}


_AHEAD_LOCK = threading.Lock()
_AHEAD: list = []         # the compile-ahead thread, once per process


def compile_ahead() -> threading.Thread | None:
    """Compile the projector's kernels in a background thread: the thread, or None.

    On an empty numba cache each kernel is compiled where it is first called, one after the
    other, on one core (about 15 s for the three on the 16 MP camera); called where the
    projector is chosen, before its tables and the image's line of sight, they compile while
    that work runs, in the order the reconstruction needs them. A call of a kernel still being
    compiled waits for it (numba's compiler lock) and never compiles it twice; kernels numba
    has cached load in a fraction of a second. Started once per process (None after that); a
    failure leaves the reconstruction to compile what it needs, with the same results.
    """
    with _AHEAD_LOCK:
        if _AHEAD:
            return None
        work = list(kernel_signatures().items())
        thread = threading.Thread(target=_compile_each, args=(work,), daemon=True,
                                  name="plenopiv-compile-ahead")
        _AHEAD.append(thread)
    thread.start()
    return thread


def _compile_each(work) -> None:
    for kernel, signature in work:
        try:
            kernel.compile(signature)
        except Exception:           # the caller compiles it on its first call instead
            return


def lenslet_weights_reference(proj: LensletProjector) -> np.ndarray:
    """Return W of a small projector as a dense float64 (n_pixels, n_voxels) array.

    The plain-NumPy twin of the kernels, from the same per-lenslet tables.
    """
    g = proj.grid
    nz, ny, nx = g.shape
    xe = g.origin[0] + (np.arange(nx + 1) - 0.5) * g.voxel[0]
    ye = g.origin[1] + (np.arange(ny + 1) - 0.5) * g.voxel[1]
    s, le, r = proj._slices, proj._lens, proj._rays
    w = np.zeros((proj.n_pixels, g.n_voxels))
    for i in range(proj.n_pixels):
        lens, lr, lc = r["ray_lens"][i], r["ray_r"][i], r["ray_c"][i]
        for k in range(nz):
            tk = s["t"][k]
            mx = (1 - tk) * le["u_col"][lens, lc] + tk * le["xf_x"][lens]
            my = (1 - tk) * le["u_row"][lens, lr] + tk * le["xf_y"][lens]
            fx = np.diff(_box_sum_cdf_np(xe - mx, s["al"][k], s["be"][k]))
            fy = np.diff(_box_sum_cdf_np(ye - my, s["al"][k], s["be"][k]))
            block = r["ray_scale"][i] * s["factor"][k] * fy[:, None] * fx[None, :]
            w[r["ray_pos"][i], k * ny * nx:(k + 1) * ny * nx] = block.ravel()
    return w


def _box_sum_cdf_np(y, alpha, beta):
    """Return the CDF at offsets ``y`` (metres) from the centre of a sum of two uniforms.

    Widths ``alpha`` and ``beta`` (metres): the trapezoid's piecewise-quadratic closed form.
    """
    lo, hi = min(alpha, beta), max(alpha, beta)
    if lo <= 1e-9 * hi:
        return np.clip(y / hi + 0.5, 0.0, 1.0)
    corners = (-0.5 * (lo + hi), -0.5 * (hi - lo), 0.5 * (hi - lo), 0.5 * (lo + hi))
    r2 = [np.maximum(y - p, 0.0) ** 2 for p in corners]
    return (r2[0] - r2[1] - r2[2] + r2[3]) / (2.0 * lo * hi)


def matrix_free_projector(lf: LightField, grid: VolumeGrid):
    """Return the fastest matrix-free projector that takes ``lf``'s lattice.

    The separable :class:`~plenopiv.reconstruction.lattice.LatticeProjector` for an axis-aligned
    square lattice, else :class:`LensletProjector`.
    """
    from plenopiv.reconstruction.lattice import LatticeProjector

    try:
        return LatticeProjector.from_light_field(lf, grid)
    except ReconstructionError:         # not separable: rotated, hexagonal or irregular
        return LensletProjector.from_light_field(lf, grid)


def estimate_lenslet_gb(lf: LightField, grid: VolumeGrid) -> float:
    """Peak memory of a SMART reconstruction with :class:`LensletProjector`, GB.

    About twelve float32 volumes (estimate, update, column sums, first guess, masks), the
    rays with their views' copies (~120 bytes each: positions, local indices, scales of the
    projector, its normalised and selected views), the per-lenslet tables, the back
    projection's local images (float32, one box² per lenslet), and one depth slab of the
    sub-voxel line-of-sight mask (:mod:`plenopiv.reconstruction.sightline`: six refined float32
    arrays).
    """
    from plenopiv.reconstruction.geometry import SLAB_VOXELS, subcell_factors

    n_lens = len(np.unique(lf.lenslet)) if lf.n_rays else 0
    box = int(math.ceil(2.0 * math.sqrt(lf.n_rays / max(n_lens, 1) / math.pi))) + 3
    kx, ky = subcell_factors(grid, lf.footprint)
    fine = min(SLAB_VOXELS, grid.n_voxels * kx * ky)
    total = (12 * 4 * grid.n_voxels + 120 * lf.n_rays + n_lens * (16 * box + 4 * box * box)
             + 6 * 4 * fine)
    return total / 1e9
