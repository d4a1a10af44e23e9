"""The judgement of a camera, a box and its settings: what would leave a component unmeasured.

:func:`judge` takes the camera's resolution (:func:`camera_resolution`), the ``[volume]``
grid, the ``[reconstruction]`` and ``[piv]`` settings and, where known, the seeding, and
returns :class:`Finding` s: the figure, what it costs, what to change. :func:`choose_unset`
picks the settings a user left unset. ``plenopiv plan`` prints the findings; ``reconstruct``,
``piv``, ``run`` and ``track`` warn with them before their work (:func:`judge_experiment`)
and record them in their products. Each threshold is a measured figure, cited where it is
defined (docs/methods.md#settings-judgement). Computation only: printing belongs to the CLI.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import CameraModel
from plenopiv.piv.settings import MIN_WINDOW_VOX, PIVSettings
from plenopiv.reconstruction.choose import (
    depth_binning_for,
    model_projector_cost,
    subdivision_for,
    sweep_cost,
    wanted_subdivision,
)
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.workflow.rates import vectors_per_pass

if TYPE_CHECKING:
    from plenopiv.config.experiment import Experiment

#: Lateral voxel per lenslet footprint: half-footprint voxels remove the peak locking of
#: footprint voxels (docs/validation/vortex.md).
LATERAL_VOXEL_PER_FOOTPRINT = 0.5

#: Depth voxel per depth cell (b S_o/D): the validated grid of docs/validation/vortex.md had a
#: depth voxel of 1/4.4 cell; a particle then spans about four voxels in depth.
DEPTH_VOXEL_PER_CELL = 0.25

#: Windows (first pass, last pass) of the validated vortex runs, in lenslet footprints
#: laterally and in depth cells in depth: 32 → 24 half-footprint voxels, 16 → 12 voxels of
#: 1/4.4 cell in depth.
WINDOW_FOOTPRINTS = (16.0, 12.0)

WINDOW_DEPTH_CELLS = (3.6, 2.7)

#: Seeding density of the validated runs, particles per lenslet.
VALIDATED_PARTICLES_PER_LENSLET = 0.15

#: The last pass should give at least this many vectors along every axis (50 % overlap):
#: windows are capped at 1/2.5 of the box's voxels along an axis.
MIN_VECTORS_LAST_PASS = 4

#: A lateral working voxel (the ``[volume]`` voxel over the reconstruction's lateral
#: subdivision) this many footprints wide or wider locks displacements to whole footprints
#: and loses depth motion: on the Oseen vortex the w gain is 0.32 with footprint-wide working
#: voxels, 0.82 with half-footprint ones and 0.90 with a third (docs/validation/vortex.md,
#: "What flattens w"); the threshold lies between the last measured loss and the first
#: measured recovery.
LOCKING_VOXEL_FOOTPRINTS = 0.75

#: A PIV window shorter in depth than this many depth cells cannot hold a reconstructed
#: particle, which is one depth cell b S_o/D long (docs/methods.md#resolution-cell): its
#: depth motion is lost. On the worked example with voxel_mm = 0.25 the w gain is 0.03 with
#: windows 0.67 cell deep and 0.53 with 1.8 cells (docs/methods.md#settings-judgement); the
#: example's own last window is 1.5 cells deep, the validated ones 2.7.
MIN_WINDOW_DEPTH_CELLS = 1.0

#: The normalised median test compares a vector with its 3 x 3 x 3 neighbourhood
#: (docs/methods.md#outlier-test): fewer vectors than this along an axis leave every vector
#: on the border, where its neighbours are extrapolated.
MIN_VECTORS_ALONG_AXIS = 3

#: Seeding (particles per lenslet) at which the correlation was validated: the Oseen and Hill
#: vortices at 0.15 and 0.3 (docs/validation/vortex.md).
VALIDATED_SEEDING = (0.15, 0.3)

#: Seeding at which the tracking was validated: 0.05 to 0.3 (docs/validation/tracking.md,
#: density sweep).
VALIDATED_TRACKING_SEEDING = (0.05, 0.3)

#: Particles found over particles seeded in the box: 0.71-0.79 on the worked example (six
#: renders, docs/methods.md#settings-judgement), 0.96 / (1 - 0.11) = 1.08 at 0.1 per lenslet
#: (detection and ghost rates, docs/validation/field_quality.md). A count from the particle
#: table is outside the validated seeding only beyond these ratios of its ends.
PARTICLE_COUNT_RATIO = (0.70, 1.08)

#: Severities of a :class:`Finding`: ``"warning"`` (a component unmeasured or a run that
#: fails), ``"advice"`` (``plan`` only: a better setting), ``"chosen"`` (an unset setting chosen).
SEVERITIES = ("warning", "advice", "chosen")


@dataclass(frozen=True)
class Camera:
    """The camera's resolution near the focal plane (effective coordinates), metres.

    ``projector_cost``: the time per working voxel of the projector its lattice takes
    (:func:`~plenopiv.reconstruction.choose.model_projector_cost`), which bounds the
    ``"auto"`` lateral subdivision.
    """

    name: str
    footprint: float
    depth_cell: float
    near_focus: float
    field_of_view: tuple[float, float]
    f_number: float
    object_distance: float
    magnification: float
    n_lenslets: int
    projector_cost: float = 1.0

    def to_dict(self) -> dict:
        """Plain JSON values (SI units)."""
        return {**dataclasses.asdict(self), "field_of_view": list(self.field_of_view)}

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        """The inverse of :meth:`to_dict`."""
        return cls(**{**d, "field_of_view": tuple(d["field_of_view"])})


@dataclass(frozen=True)
class Finding:
    """One judgement of a setting.

    ``kind``: what is judged (``lateral_voxel``, ``depth_window``, ``vectors``,
    ``windows_fit``, ``seeding``, ``field_of_view``, ``voxel``, ``windows``, ``near_focus``);
    ``severity``: one of :data:`SEVERITIES`; ``setting``: the key to change; ``figure`` in
    ``unit`` against ``limit``; ``message``: the figure and what it costs; ``change``: what
    to change.
    """

    kind: str
    severity: str
    setting: str
    figure: float
    unit: str
    limit: float | None
    message: str
    change: str = ""

    @property
    def text(self) -> str:
        """The finding in one line: the message, then what to change."""
        return f"{self.message}; {self.change}" if self.change else self.message

    def to_dict(self) -> dict:
        """Plain JSON values."""
        return {**dataclasses.asdict(self), "text": self.text}


def camera_resolution(camera: CameraModel, f_number: float | None = None) -> Camera:
    """Footprint, depth cell, near-focus zone and field of view of ``camera`` (effective)."""
    from plenopiv.camera.resolution import resolution_cell
    from plenopiv.synthetic.images import field_of_view

    n = camera.main_lens.f_number if f_number is None else f_number
    lat, dep = resolution_cell(camera, n)
    return Camera(name=camera.name, footprint=lat, depth_cell=dep, near_focus=dep,
                  field_of_view=field_of_view(camera, 0.0), f_number=n,
                  object_distance=camera.object_distance, magnification=camera.magnification,
                  n_lenslets=camera.microlens_array.count,
                  projector_cost=model_projector_cost(camera))


def recommended_voxel(cam: Camera) -> tuple[float, float, float]:
    """``(dx, dy, dz)``: half a footprint laterally, a quarter of the depth cell in depth."""
    lat = LATERAL_VOXEL_PER_FOOTPRINT * cam.footprint
    return (lat, lat, DEPTH_VOXEL_PER_CELL * cam.depth_cell)


def _even(w: float, lo: int = 6) -> int:
    return max(lo, 2 * int(math.floor(w / 2 + 0.25)))


def recommended_windows(cam: Camera, voxel, shape=None) -> tuple[tuple[int, int, int], ...]:
    """Windows ``(wz, wy, wx)`` (first pass, last pass) in voxels of ``voxel``.

    The validated physical sizes (:data:`WINDOW_FOOTPRINTS`, :data:`WINDOW_DEPTH_CELLS`),
    rounded to even voxels; with ``shape`` (the box, ``(nz, ny, nx)`` voxels) the last window
    is capped so that the last pass gives :data:`MIN_VECTORS_LAST_PASS` vectors along every
    axis, and the first is at most 4/3 of it. On the small camera with a box 4.5 depth cells
    deep, capping the depth window (3.6 → 1.5 cells) raised the correlation of u with a
    Lamb-Oseen vortex from -0.05 to 0.93 (the vortex's depth scale is one depth cell).
    """
    first, last = [], []
    for axis in range(3):                    # z, y, x
        if axis == 0:
            size = [c * cam.depth_cell / voxel[2] for c in WINDOW_DEPTH_CELLS]
        else:
            size = [f * cam.footprint / voxel[2 - axis] for f in WINDOW_FOOTPRINTS]
        w_first, w_last = _even(size[0]), _even(size[1])
        if shape is not None:
            cap = _even(2 * shape[axis] / (MIN_VECTORS_LAST_PASS + 1), lo=4)
            if w_last > cap:
                w_last = cap
                w_first = min(w_first, _even(4 * w_last / 3, lo=4))
            w_first = min(w_first, shape[axis])
        first.append(w_first)
        last.append(w_last)
    return (tuple(first), tuple(last))


def snap_grid(grid: VolumeGrid, voxel) -> VolumeGrid:
    """``grid``'s box on voxels of about ``voxel`` (m), whole voxels filling it."""
    b = grid.bounds
    return VolumeGrid.from_bounds(b[0], b[1], b[2], voxel=np.asarray(voxel, float))


def _mm(m: float) -> str:
    """A length in metres as mm, short: 3 decimals at most, no trailing zeros."""
    s = f"{m * 1e3:.3f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def windows_toml(windows) -> str:
    """``windows`` as the value of ``[piv] windows``."""
    return "[" + ", ".join("[" + ", ".join(str(int(v)) for v in w) + "]" for w in windows) + "]"


# ---- the findings ----------------------------------------------------------------------------


def camera_subdivision(cam: Camera, grid: VolumeGrid, setting: str | int = "auto",
                       depth_binning: str | int = "auto") -> tuple[int, int]:
    """The lateral cut ``(ky, kx)`` of ``grid`` the reconstruction takes on this camera.

    ``setting`` and ``depth_binning``: ``[reconstruction] lateral_subdivision`` and
    ``depth_binning``.
    """
    return subdivision_for(cam.footprint, grid, setting, cost=cam.projector_cost,
                           depth_binning=depth_binning_for(cam.depth_cell, grid,
                                                           depth_binning))


def lateral_voxel_finding(cam: Camera, grid: VolumeGrid, subdivision: tuple[int, int],
                          depth_binning: str | int = "auto") -> Finding | None:
    """A warning when the lateral working voxel is :data:`LOCKING_VOXEL_FOOTPRINTS` or wider.

    ``subdivision``: ``(ky, kx)`` the reconstruction cuts each voxel into;
    ``depth_binning``: the ``[reconstruction]`` setting.
    """
    fp = cam.footprint
    ky, kx = subdivision
    vox = max(grid.voxel[0], grid.voxel[1])
    work = max(grid.voxel[0] / kx, grid.voxel[1] / ky)
    if work / fp < LOCKING_VOXEL_FOOTPRINTS:
        return None
    sub = "no lateral subdivision" if (ky, kx) == (1, 1) else f"a {ky} x {kx} subdivision"
    auto = camera_subdivision(cam, grid, "auto", depth_binning)
    wanted = wanted_subdivision(fp, grid.voxel, "auto")
    if auto != wanted:      # "auto" gave up the finer cut for the size of the grid
        more = sweep_cost(*wanted) / sweep_cost(ky, kx)
        fix = (f"set [reconstruction] lateral_subdivision = {max(wanted)} ({wanted[0]} x "
               f"{wanted[1]}: about {more:.2g} times the time of the reconstruction's sweeps "
               f"and {wanted[0] * wanted[1] // (ky * kx)} times its working voxels), or "
               "reconstruct a smaller box")
    else:
        fix = (f"set [reconstruction] lateral_subdivision = \"auto\" ({auto[0]} x {auto[1]} "
               f"here) or [volume] voxel_mm = {_mm(LATERAL_VOXEL_PER_FOOTPRINT * fp)} (half a "
               "footprint)")
    return Finding(
        "lateral_voxel", "warning", "[reconstruction] lateral_subdivision", work / fp,
        "footprint", LOCKING_VOXEL_FOOTPRINTS,
        f"lateral voxel {_mm(vox)} mm is {vox / fp:.2g} footprint ({_mm(fp)} mm) and the "
        f"reconstruction works on it with {sub}: displacements lock to whole footprints and "
        "depth motion is under-measured (w gain 0.32 on footprint-wide working voxels, 0.90 "
        "on a third of a footprint, docs/validation/vortex.md)", fix)


def depth_window_finding(cam: Camera, grid: VolumeGrid, piv: PIVSettings) -> Finding | None:
    """A warning when a pass's window is shorter in depth than a reconstructed particle."""
    dz, cell = grid.voxel[2], cam.depth_cell
    short = min(piv.windows, key=lambda w: w[0])
    ratio = short[0] * dz / cell
    if ratio >= MIN_WINDOW_DEPTH_CELLS:
        return None
    need = max(MIN_WINDOW_VOX, math.ceil(MIN_WINDOW_DEPTH_CELLS * cell / dz - 1e-9))
    rec = recommended_windows(cam, grid.voxel, grid.shape)
    change = (f"make the windows at least {need} voxels deep, e.g. [piv] windows = "
              f"{windows_toml(rec)} for this voxel and box, or plan's recommended voxel "
              "and windows")
    if min(w[0] for w in rec) < need:
        change = (f"make the windows at least {need} voxels deep and the box deeper: z_mm "
                  f"spans {grid.shape[0] * dz / cell:.2g} depth cells, too few for windows "
                  f"of one cell with {MIN_VECTORS_ALONG_AXIS} vectors along z")
    return Finding(
        "depth_window", "warning", "[piv] windows", ratio, "depth cell",
        MIN_WINDOW_DEPTH_CELLS,
        f"the PIV window {list(short)} voxels (z, y, x) is {_mm(short[0] * dz)} mm deep, "
        f"{ratio:.2g} of a reconstructed particle's depth elongation (one depth cell, "
        f"{_mm(cell)} mm): a window shorter than a particle cannot follow its depth motion, "
        "and w is lost (w gain 0.03 at 0.67 cell on the worked example, "
        "docs/methods.md#settings-judgement)", change)


def window_findings(grid: VolumeGrid, piv: PIVSettings) -> list[Finding]:
    """Warnings when a pass's windows exceed the volume or the last pass gives too few vectors.

    Too few: under :data:`MIN_VECTORS_ALONG_AXIS` along an axis.
    """
    windows, passes = piv.windows, piv.passes
    vectors = vectors_per_pass(grid.shape, windows, piv.overlap, passes)
    for k in range(len(vectors)):
        w = windows[min(k, len(windows) - 1)]
        short = [(ax, wk, nk) for ax, wk, nk in zip("zyx", w, grid.shape, strict=True) if wk > nk]
        if short:
            parts = [f"{ax}: window {wk} voxels > {nk} voxels of the volume; make {ax}_mm span "
                     f"at least {wk * grid.voxel['xyz'.index(ax)] * 1e3:.3g} mm"
                     for ax, wk, nk in short]
            return [Finding(
                "windows_fit", "warning", "[piv] windows", float(k + 1), "pass", None,
                f"the PIV windows of pass {k + 1} do not fit the volume {list(grid.shape)} "
                f"(z, y, x): {'; '.join(parts)}",
                "or use smaller [piv] windows; every pair would fail with \"windows larger "
                "than the volume\"")]
    last = vectors[-1]
    thin = [ax for ax, n in zip("zyx", last, strict=True) if n < MIN_VECTORS_ALONG_AXIS]
    if not thin:
        return []
    return [Finding(
        "vectors", "warning", "[piv] windows", float(min(last)), "vectors",
        float(MIN_VECTORS_ALONG_AXIS),
        f"the last pass gives {last[0]} × {last[1]} × {last[2]} vectors (z, y, x): fewer "
        f"than {MIN_VECTORS_ALONG_AXIS} along {', '.join(thin)}, so the median test has few "
        "neighbours there (docs/methods.md#outlier-test)",
        "enlarge the box or shrink the windows along it")]


def field_of_view_finding(cam: Camera, grid: VolumeGrid) -> Finding | None:
    """A warning when the box reaches laterally beyond the field of view at the focal plane."""
    b = grid.bounds
    out, reach = [], 0.0
    for i, ax in enumerate("xy"):
        f = cam.field_of_view[i]
        if b[i, 0] < -f * 1.001 or b[i, 1] > f * 1.001:
            out.append(f"{ax}_mm = [{_mm(b[i, 0])}, {_mm(b[i, 1])}] reaches beyond "
                       f"±{f * 1e3:.3g} mm")
            reach = max(reach, max(-b[i, 0], b[i, 1]) / f)
    if not out:
        return None
    return Finding("field_of_view", "warning", "[volume] x_mm, y_mm", reach,
                   "half field of view", 1.0,
                   f"the box leaves the field of view at the focal plane: {'; '.join(out)}",
                   "voxels outside are seen by few pixels and hold noise")


def lenslets_in_box(cam: Camera, grid: VolumeGrid) -> float:
    """Lenslets whose footprints cover the box laterally (the part in the field of view)."""
    b = grid.bounds
    fx, fy = cam.field_of_view
    wx = min(b[0, 1], fx) - max(b[0, 0], -fx)
    wy = min(b[1, 1], fy) - max(b[1, 0], -fy)
    return cam.n_lenslets * max(wx, 0.0) * max(wy, 0.0) / (4.0 * fx * fy)


def _seeding_figures(cam, grid, n_particles, particles_per_lenslet):
    lenslets = lenslets_in_box(cam, grid)
    if n_particles is None:
        return lenslets, particles_per_lenslet
    return lenslets, (n_particles / lenslets if lenslets > 0 else math.nan)


def seeding_finding(cam: Camera, grid: VolumeGrid, *, n_particles: float | None = None,
                    particles_per_lenslet: float | None = None, purpose: str = "velocimetry",
                    piv: PIVSettings | None = None) -> Finding | None:
    """A warning when the seeding is far from the one the chain was validated at.

    Give the particles a table found in ``grid`` (``n_particles``, over
    :func:`lenslets_in_box`), or the seeding a user states (``particles_per_lenslet``).
    Validated: :data:`VALIDATED_SEEDING` for the correlation, or
    :data:`VALIDATED_TRACKING_SEEDING` for ``purpose = "tracking"``; a count is judged against
    that range widened by :data:`PARTICLE_COUNT_RATIO`. ``piv``: the experiment's, to name the
    seeding its response is measured at.
    """
    lenslets, ppl = _seeding_figures(cam, grid, n_particles, particles_per_lenslet)
    if not ppl >= 0:
        return None
    lo_v, hi_v = VALIDATED_TRACKING_SEEDING if purpose == "tracking" else VALIDATED_SEEDING
    lo, hi = lo_v, hi_v
    if n_particles is not None:
        lo, hi = lo_v * PARTICLE_COUNT_RATIO[0], hi_v * PARTICLE_COUNT_RATIO[1]
    if lo * (1 - 1e-9) <= ppl <= hi * (1 + 1e-9):
        return None
    source = ("docs/validation/tracking.md" if purpose == "tracking"
              else "docs/validation/vortex.md")
    found = ("a seeding of" if n_particles is None else
             f"{n_particles:.0f} particles found over the box's {lenslets:.0f} lenslets: about")
    message = (f"{found} {ppl:.2g} particles per lenslet, {'below' if ppl < lo else 'above'} "
               f"the {lo_v:g}-{hi_v:g} at which the {purpose} was validated ({source})")
    if ppl < lo:
        change = ("seed more densely; for this recording, larger [piv] windows (the particles "
                  "per window grow with its volume)"
                  + ("" if purpose == "tracking" else
                     ", or plenopiv track (validated from 0.05 per lenslet)"))
    else:
        change = ("seed more sparsely: denser fields hold more ghost particles and find fewer "
                  "of the real ones (docs/validation/field_quality.md)")
    if piv is not None and piv.uncertainty == "response":
        change += (f"; [piv] response_particles_per_lenslet = {ppl:.2g} measures the "
                   "uncertainty at this seeding")
    return Finding("seeding", "warning", "seeding", float(ppl), "particles per lenslet",
                   lo if ppl < lo else hi, message, change)


# ---- advice (plan) ---------------------------------------------------------------------------


def voxel_advice(cam: Camera, grid: VolumeGrid, subdivision) -> list[Finding]:
    """Advice when the voxel is far from half a footprint laterally or a quarter depth cell."""
    out: list[Finding] = []
    fp, cell = cam.footprint, cam.depth_cell
    rec = snap_grid(grid, recommended_voxel(cam)).voxel
    vx, vy, vz = grid.voxel
    lat = max(vx, vy)
    locked = subdivision is not None and lateral_voxel_finding(cam, grid, subdivision)
    if lat > LOCKING_VOXEL_FOOTPRINTS * fp and subdivision is not None and not locked:
        ky, kx = subdivision
        out.append(Finding(
            "voxel", "advice", "[volume] voxel_mm", lat / fp, "footprint", None,
            f"lateral voxel {_mm(lat)} mm is {lat / fp:.2g} footprint ({_mm(fp)} mm), "
            f"reconstructed on a {ky} x {kx} subdivision: half-footprint voxels lower the "
            "lateral error (0.072 → 0.050 footprint rms on the Oseen vortex at 0.3 per "
            "lenslet, docs/validation/vortex.md)", f"use {_mm(rec[0])} mm (half a footprint)"))
    elif lat < 0.3 * fp:
        out.append(Finding(
            "voxel", "advice", "[volume] voxel_mm", lat / fp, "footprint", 0.3,
            f"lateral voxel {_mm(lat)} mm is {lat / fp:.2g} footprint: finer than a third of a "
            "footprint costs voxels without resolving more", f"{_mm(rec[0])} mm is enough"))
    elong = cell / vz
    if elong > 6 or elong < 2:
        what = (f"is 1/{elong:.2g} of the depth cell ({_mm(cell)} mm): a particle spans about "
                f"{elong:.0f} voxels in depth" if elong > 6 else
                f"is {1 / elong:.2g} depth cells: particles are under two voxels long in depth")
        out.append(Finding(
            "voxel", "advice", "[volume] voxel_mm", vz / cell, "depth cell",
            1 / 6 if elong > 6 else 0.5, f"depth voxel {_mm(vz)} mm {what}",
            f"use {_mm(rec[2])} mm (a quarter of the cell), which is what the recommended "
            "windows are sized for"))
    return out


def window_advice(cam: Camera, grid: VolumeGrid, piv: PIVSettings) -> list[Finding]:
    """Advice when the first or last windows differ much from the recommended physical size."""
    out: list[Finding] = []
    windows = piv.windows
    rec_grid = snap_grid(grid, recommended_voxel(cam))
    rec_win = recommended_windows(cam, rec_grid.voxel, rec_grid.shape)
    rv = np.array(rec_grid.voxel[::-1])                       # z, y, x in m
    own = np.array(grid.voxel[::-1])
    for k, (w, r) in enumerate(zip((windows[0], windows[-1]), rec_win, strict=True)):
        mine, theirs = np.array(w) * own, np.array(r) * rv
        ratio = mine / theirs
        if np.any(ratio < 0.6) or np.any(ratio > 1.7):
            which = "first" if k == 0 else "last"
            out.append(Finding(
                "windows", "advice", "[piv] windows", float(np.max(np.abs(np.log(ratio)))),
                "log ratio", None,
                f"the {which} window {list(w)} voxels is "
                f"{' x '.join(_mm(v) for v in mine)} mm (z, y, x)",
                f"for this camera and box use about {' x '.join(_mm(v) for v in theirs)} mm, "
                f"i.e. {list(r)} voxels of the recommended voxel"))
        if len(windows) == 1:
            break
    capped = [ax for ax, r, ful in zip("zyx", rec_win[-1],
                                       recommended_windows(cam, rec_grid.voxel)[-1], strict=True)
              if r < ful]
    if capped:
        out.append(Finding(
            "windows", "advice", "[piv] windows", float(len(capped)), "axes", None,
            f"this box is small along {', '.join(capped)} for the validated windows "
            f"({WINDOW_FOOTPRINTS[-1]:g} footprints, {WINDOW_DEPTH_CELLS[-1]:g} depth cells): "
            f"the recommended windows are cut to give {MIN_VECTORS_LAST_PASS} vectors along "
            "every axis (finer, noisier vectors)", "a larger box keeps the validated size"))
    return out


def near_focus_advice(cam: Camera, grid: VolumeGrid) -> Finding | None:
    """Advice when the whole box lies within the near-focus zone."""
    b, nf = grid.bounds, cam.near_focus
    if not (b[2, 0] >= -nf and b[2, 1] <= nf):
        return None
    return Finding("near_focus", "advice", "[volume] z_mm", float(np.max(np.abs(b[2])) / nf),
                   "depth cell", 1.0,
                   f"the whole box lies in the near-focus zone |Z| < {nf * 1e3:.3g} mm, where a "
                   "particle lights one lenslet and depth motion is under-measured",
                   "extend z_mm beyond it")


# ---- all of them -----------------------------------------------------------------------------


def judge(cam: Camera | None, grid: VolumeGrid,
          reconstruction: ReconstructionSettings | None = None, piv: PIVSettings | None = None,
          *, subdivision: tuple[int, int] | None = None, n_particles: float | None = None,
          particles_per_lenslet: float | None = None, purpose: str = "velocimetry",
          advice: bool = False) -> tuple[Finding, ...]:
    """Every finding on a camera's box and settings: warnings first, then (``advice``) advice.

    ``cam``: :func:`camera_resolution` of the effective camera (None: only what needs no
    camera, the windows against the box). ``subdivision``: the reconstruction's lateral
    subdivision; by default the one ``reconstruction`` asks for (None without either: the
    lateral voxel is not judged). ``n_particles`` (found) or ``particles_per_lenslet``
    (stated): the seeding, judged for ``purpose`` ("velocimetry" or "tracking").
    """
    out: list[Finding | None] = []
    if subdivision is None and reconstruction is not None and cam is not None:
        subdivision = camera_subdivision(cam, grid, reconstruction.lateral_subdivision,
                                         reconstruction.depth_binning)
    if cam is not None and subdivision is not None:
        out.append(lateral_voxel_finding(cam, grid, subdivision,
                                         "auto" if reconstruction is None
                                         else reconstruction.depth_binning))
    if piv is not None:
        if cam is not None:
            out.append(depth_window_finding(cam, grid, piv))
        out += window_findings(grid, piv)
    if cam is not None:
        out.append(field_of_view_finding(cam, grid))
        if n_particles is not None or particles_per_lenslet is not None:
            out.append(seeding_finding(cam, grid, n_particles=n_particles,
                                       particles_per_lenslet=particles_per_lenslet,
                                       purpose=purpose, piv=piv))
        if advice:
            out += voxel_advice(cam, grid, subdivision)
            if piv is not None:
                out += window_advice(cam, grid, piv)
            out.append(near_focus_advice(cam, grid))
    return tuple(f for f in out if f is not None)


def choose_unset(cam: Camera | None, grid: VolumeGrid, piv: PIVSettings,
                 given: frozenset[str] | None) -> tuple[PIVSettings, tuple[Finding, ...]]:
    """``piv`` with the settings a user left unset chosen for ``cam`` and ``grid``.

    ``given``: the ``"table.key"`` settings the user gave (:func:`given_settings`); None
    takes every setting as given. ``[piv] windows`` unset: :func:`recommended_windows` for
    the grid's voxel and box (only the last when ``[piv] passes`` is 1). Returns the settings
    and a ``"chosen"`` finding for each setting chosen; a given setting is never changed.
    """
    if cam is None or given is None or "piv.windows" in given:
        return piv, ()
    windows = recommended_windows(cam, grid.voxel, grid.shape)
    if piv.passes < len(windows):
        windows = windows[-1:]
    chosen = dataclasses.replace(piv, windows=windows)
    w = windows[-1]
    return chosen, (Finding(
        "windows", "chosen", "[piv] windows", float(w[0] * grid.voxel[2] / cam.depth_cell),
        "depth cell", None,
        f"[piv] windows not set: chose {windows_toml(windows)} voxels (z, y, x), the last "
        f"{_mm(w[2] * grid.voxel[0])} x {_mm(w[1] * grid.voxel[1])} x "
        f"{_mm(w[0] * grid.voxel[2])} mm (x, y, z): the validated {WINDOW_FOOTPRINTS[-1]:g} "
        f"footprints and {WINDOW_DEPTH_CELLS[-1]:g} depth cells (docs/validation/vortex.md), "
        f"cut where this box needs it to give {MIN_VECTORS_LAST_PASS} vectors along every "
        "axis"),)


def given_settings(experiment: Experiment) -> frozenset[str] | None:
    """The settings an experiment file gives, as ``"table.key"``; None for one built in Python.

    An experiment made in Python (no source table) is taken as it is: every setting given.
    """
    source = experiment.source
    if not source:
        return None
    return frozenset(f"{table}.{key}" for table, keys in source.items()
                     if isinstance(keys, dict) for key in keys)


@dataclass(frozen=True)
class Judgement:
    """The findings on one reconstruction or pair, and what they were judged on.

    ``camera``: the resolution (None where unknown); ``subdivision``: the reconstruction's
    lateral subdivision; ``n_particles``: particles found (one volume, or a pair's mean);
    ``depth_binning``: the grid's depth slices per working slice.
    """

    camera: Camera | None
    grid: VolumeGrid
    findings: tuple[Finding, ...] = ()
    subdivision: tuple[int, int] | None = None
    n_particles: float | None = None
    depth_binning: int | None = None

    @property
    def warnings(self) -> tuple[Finding, ...]:
        """The findings of severity ``"warning"``."""
        return tuple(f for f in self.findings if f.severity == "warning")

    def with_seeding(self, n_particles: float, *, purpose: str = "velocimetry",
                     piv: PIVSettings | None = None) -> tuple[Judgement, Finding | None]:
        """The judgement with the seeding of ``n_particles`` found, and that finding (or None)."""
        found = None
        if self.camera is not None:
            found = seeding_finding(self.camera, self.grid, n_particles=n_particles,
                                    purpose=purpose, piv=piv)
        extra = () if found is None else (found,)
        return dataclasses.replace(self, findings=self.findings + extra,
                                   n_particles=float(n_particles)), found

    def record(self) -> dict:
        """Plain JSON values: the products' ``judgement`` attribute and the ``--json`` key."""
        cam = self.camera
        lenslets = None if cam is None else lenslets_in_box(cam, self.grid)
        ppl = (None if self.n_particles is None or not lenslets
               else self.n_particles / lenslets)
        return {"findings": [f.to_dict() for f in self.findings],
                "camera": None if cam is None else cam.to_dict(),
                "lateral_subdivision": None if self.subdivision is None else
                list(self.subdivision),
                "depth_binning": self.depth_binning,
                "lenslets_in_box": lenslets, "n_particles": self.n_particles,
                "particles_per_lenslet": ppl}


def judge_experiment(experiment: Experiment, cam: Camera | None, *,
                     given: frozenset[str] | None | str = "file",
                     purpose: str = "velocimetry") -> tuple[Experiment, Judgement]:
    """The experiment with its unset settings chosen (:func:`choose_unset`), and the findings.

    ``cam``: :func:`camera_resolution` of the calibrated (effective) camera at the
    reconstruction's f-number. ``given``: the settings the user gave; ``"file"`` (default):
    those of the experiment file (:func:`given_settings`). The findings are the chosen
    settings and the warnings of :func:`judge`, before any work; add the seeding once
    particles are found (:meth:`Judgement.with_seeding`).
    """
    if given == "file":
        given = given_settings(experiment)
    piv, chosen = choose_unset(cam, experiment.volume, experiment.piv, given)
    if chosen:
        experiment = dataclasses.replace(experiment, piv=piv)
    rec = experiment.reconstruction
    sub = (None if cam is None else
           camera_subdivision(cam, experiment.volume, rec.lateral_subdivision,
                              rec.depth_binning))
    kz = (None if cam is None else
          depth_binning_for(cam.depth_cell, experiment.volume, rec.depth_binning))
    found = judge(cam, experiment.volume, rec, piv, subdivision=sub, purpose=purpose)
    return experiment, Judgement(cam, experiment.volume, chosen + found, sub,
                                 depth_binning=kz)
