"""A measured vector field against the truth: gain, bias, rms and correlation per component.

One implementation serves ``plenopiv compare`` (:func:`compare_products`) and the synthetic
cases (``plenopiv demo``, ``plenopiv validate``): the truth at the vectors
(:func:`true_displacement` of a known flow, or :func:`window_mean_displacement` of the true
particles, or another vectors product), the vectors used (:func:`inner_vectors`) and the
figures per component, overall and in depth bands (:func:`field_accuracy`, on
:func:`plenopiv.workflow.accuracy.gain_bias_rms`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plenopiv.camera.grid import VolumeGrid
from plenopiv.errors import ComparisonError
from plenopiv.workflow.accuracy import gain_bias_rms

__all__ = ["COMPONENTS", "Truth", "compare_products", "field_accuracy", "inner_vectors",
           "pair_truth", "true_displacement", "vectors_truth", "window_mean_displacement"]

#: The displacement components, in the order of the arrays' first axis.
COMPONENTS = ("u", "v", "w")

#: Product kind of a synthetic pair file (``plenopiv simulate pair``).
PAIR_PRODUCT = "synthetic pair"
#: ``truth_kind`` of a comparison with a synthetic pair.
SIMULATED_PAIR = "simulated pair"

#: A rebuilt flow counts as the recorded one when it moves every recorded particle from its
#: position A to its position B within this fraction of the largest displacement (plus 1e-12 m).
FLOW_TOLERANCE = 1e-6


def true_displacement(vectors, flow, dt) -> np.ndarray:
    """The flow's displacement at the window centres, (3, nz, ny, nx), metres.

    PIV measures the displacement of the particles around a window centre between the
    exposures, i.e. of the material point that sits at the centre half-way between them.
    ``dt``: seconds between the exposures.
    """
    from plenopiv.synthetic.flows import advect

    Z, Y, X = np.meshgrid(vectors.z, vectors.y, vectors.x, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    d = advect(flow, pts, dt / 2) - advect(flow, pts, -dt / 2)
    return d.T.reshape((3,) + X.shape)


def inner_vectors(vectors, grid: VolumeGrid, window_vox) -> np.ndarray:
    """Vectors whose window lies inside the volume, bool ``(nz, ny, nx)``.

    A vector counts when its centre is at least half a window ``window_vox`` ``(z, y, x)``
    from every face of ``grid``; a window that touches a face is inside (a millionth of a
    voxel of rounding allowed, so that the answer does not depend on how the grid's origin
    rounds).
    """
    zz, yy, xx = np.meshgrid(vectors.z, vectors.y, vectors.x, indexing="ij")
    inner = np.ones(xx.shape, bool)
    for c, (lo, hi), w, d in zip((xx, yy, zz), grid.bounds, window_vox[::-1], grid.voxel,
                                 strict=True):
        margin = (0.5 * w - 1e-6) * d
        inner &= (c >= lo + margin) & (c <= hi - margin)
    return inner


def window_mean_displacement(vectors, positions, displacement,
                             window_m) -> tuple[np.ndarray, np.ndarray]:
    """Mean displacement of the particles inside each vector's window.

    Parameters
    ----------
    vectors
        Anything with the window centres ``x``, ``y``, ``z`` (1-D, metres, evenly spaced).
    positions : (N, 3)
        Particle positions (x, y, z), metres: the mid-points between the exposures, where
        PIV places the displacement it measures.
    displacement : (N, 3)
        Their displacements (x, y, z), metres.
    window_m : (wx, wy, wz)
        Window edges, metres; a particle on an edge counts.

    Returns
    -------
    mean : (3, nz, ny, nx)
        Mean displacement (u, v, w), metres; NaN in a window without particles.
    count : (nz, ny, nx) int
        Particles in each window.
    """
    p = np.asarray(positions, float).reshape(-1, 3)
    d = np.asarray(displacement, float).reshape(-1, 3)
    axes = [np.asarray(a, float) for a in (vectors.x, vectors.y, vectors.z)]
    shape = tuple(len(a) for a in axes[::-1])
    first, last = [], []
    for k, (c, w) in enumerate(zip(axes, window_m, strict=True)):
        half = 0.5 * float(w)
        if len(c) > 1:
            step = float(c[1] - c[0])
            lo = np.ceil((p[:, k] - half - c[0]) / step - 1e-9).astype(np.int64)
            hi = np.floor((p[:, k] + half - c[0]) / step + 1e-9).astype(np.int64)
        else:
            inside = np.abs(p[:, k] - c[0]) <= half * (1 + 1e-9)
            lo = np.where(inside, 0, 1).astype(np.int64)
            hi = np.zeros(len(p), np.int64)
        first.append(np.maximum(lo, 0))
        last.append(np.minimum(hi, len(c) - 1))
    spans = [int(max(0, (b - a).max(initial=0))) for a, b in zip(first, last, strict=True)]
    size = int(np.prod(shape))
    count = np.zeros(size)
    sums = np.zeros((3, size))
    for ox in range(spans[0] + 1):
        for oy in range(spans[1] + 1):
            for oz in range(spans[2] + 1):
                idx = [first[0] + ox, first[1] + oy, first[2] + oz]
                sel = np.all([i <= b for i, b in zip(idx, last, strict=True)], axis=0)
                if not sel.any():
                    continue
                flat = np.ravel_multi_index((idx[2][sel], idx[1][sel], idx[0][sel]), shape)
                count += np.bincount(flat, minlength=size)
                for c in range(3):
                    sums[c] += np.bincount(flat, d[sel, c], minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, sums / np.where(count > 0, count, 1), np.nan)
    return mean.reshape((3,) + shape), count.astype(np.int64).reshape(shape)


def _component(g: dict, i: int, voxel: float) -> dict:
    """Figures of component ``i`` of a :func:`gain_bias_rms` result (voxels), metres beside."""
    return {"gain": g["gain"][i], "bias": g["bias"][i], "rms": g["rms"][i],
            "correlation": g["correlation"][i], "true_rms": g["true_rms"][i], "n": g["n"],
            "bias_m": g["bias"][i] * voxel, "rms_m": g["rms"][i] * voxel,
            "true_rms_m": g["true_rms"][i] * voxel}


def _figures(meas_vox: np.ndarray, true_vox: np.ndarray, voxel) -> dict:
    """``{"u": {...}, "v": {...}, "w": {...}}`` of (3, N) measured and true voxels."""
    g = gain_bias_rms(meas_vox, true_vox)
    return {c: _component(g, i, float(voxel[i])) for i, c in enumerate(COMPONENTS)}


def _gain_notes(figures: dict, where: str = "", components=COMPONENTS) -> list[str]:
    """Why a gain or a correlation is missing (null in JSON), one line per component."""
    notes = []
    for c in components:
        f = figures[c]
        if f["n"] == 0:
            continue
        if not np.isfinite(f["gain"]):
            notes.append(f"{where}{c}: no gain, the true {c} does not vary (rms "
                         f"{f['true_rms']:.3f} voxel)")
        elif not np.isfinite(f["correlation"]):
            notes.append(f"{where}{c}: no correlation coefficient, the measured {c} does not "
                         "vary")
    return notes


def field_accuracy(measured, truth, z, voxel, *, mask=None, bands: int = 3) -> dict:
    """Gain, bias, rms, correlation and true rms of a measured field against the truth.

    Parameters
    ----------
    measured, truth : array_like, shape (3, ...)
        Displacements (u, v, w), metres, sample for sample.
    z : array_like, shape (...)
        Depth Z of each sample, metres (for the depth bands).
    voxel : (dx, dy, dz)
        Voxel edges, metres: the unit of the figures (u in dx, v in dy, w in dz).
    mask : array_like of bool, shape (...), optional
        The samples to use (valid vectors with their windows inside the volume); samples
        where either field is not finite are left out too.
    bands : int
        Equal bands of Z between the lowest and the highest sample used (>= 1).

    Returns
    -------
    dict
        ``n_vectors`` (samples used), ``unit`` ("voxel"), ``voxel_m``, ``overall`` and each of
        ``bands`` (with ``z_m`` = [lo, hi] and ``n_vectors``): per component ``u``, ``v``,
        ``w`` a dict of ``gain`` (NaN where the true component does not vary), ``bias``,
        ``rms``, ``correlation`` (Pearson's r, NaN likewise), ``true_rms`` and ``n``, in
        voxels, and ``bias_m``, ``rms_m``, ``true_rms_m`` in metres; ``notes``, why a figure
        is missing.
    """
    if not (isinstance(bands, (int, np.integer)) and bands >= 1):
        raise ValueError(f"bands = {bands!r}: expected an integer >= 1")
    vox = np.asarray(voxel, float).reshape(3)
    m = np.asarray(measured, float).reshape(3, -1)
    t = np.asarray(truth, float).reshape(3, -1)
    zz = np.asarray(z, float).ravel()
    if m.shape != t.shape or zz.size != m.shape[1]:
        raise ValueError(f"measured {np.shape(measured)}, truth {np.shape(truth)} and z "
                         f"{np.shape(z)}: expected (3, ...), (3, ...) and (...) of one shape")
    ok = np.all(np.isfinite(m) & np.isfinite(t), axis=0) & np.isfinite(zz)
    if mask is not None:
        ok &= np.asarray(mask, bool).ravel()
    m, t, zz = m[:, ok] / vox[:, None], t[:, ok] / vox[:, None], zz[ok]
    overall = _figures(m, t, vox)
    out = {"n_vectors": int(ok.sum()), "unit": "voxel", "voxel_m": vox.tolist(),
           "overall": overall, "bands": [], "notes": _gain_notes(overall)}
    if not zz.size:
        out["notes"].append("no vector to compare: none is valid, finite and with its window "
                            "inside the volume")
        return out
    lo, hi = float(zz.min()), float(zz.max())
    edges = np.linspace(lo, hi, bands + 1)
    which = (np.clip(np.floor((zz - lo) / (hi - lo) * bands), 0, bands - 1).astype(int)
             if hi > lo else np.zeros(zz.size, int))
    for b in range(bands):
        sel = which == b
        fig = _figures(m[:, sel], t[:, sel], vox)
        out["bands"].append({"z_m": [float(edges[b]), float(edges[b + 1])],
                             "n_vectors": int(sel.sum()), **fig})
        where = f"Z {edges[b] * 1e3:.3f} to {edges[b + 1] * 1e3:.3f} mm, "
        if not sel.any():
            out["notes"].append(f"{where}no vector")
            continue
        # a band's missing gain is news only where the whole field has one
        out["notes"] += _gain_notes(fig, where, [c for c in COMPONENTS
                                                 if np.isfinite(overall[c]["gain"])])
    return out


@dataclass(frozen=True)
class Truth:
    """The true displacement at a field's vectors.

    Attributes
    ----------
    displacement : (3, nz, ny, nx)
        u, v, w, metres; NaN where there is no truth.
    kind : {"simulated pair", "vectors"}
        What the truth file is.
    at_vectors : {"flow", "window mean", "vectors"}
        How the truth was evaluated at the vectors: the recorded flow at the window centres,
        the mean displacement of the true particles inside each window, or another vectors
        product's own vectors (same grid).
    notes : tuple of str
        How, in words.
    valid : (nz, ny, nx) bool or None
        The truth's own valid vectors (a vectors product), None where every vector has one.
    """

    displacement: np.ndarray
    kind: str
    at_vectors: str
    notes: tuple[str, ...] = ()
    valid: np.ndarray | None = None


def _rebuild_flow(recorded) -> tuple[object | None, str]:
    """``(flow, "")`` of a pair's recorded ``config["flow"]``, or ``(None, why not)``."""
    from plenopiv.synthetic.flows import FLOWS

    if not isinstance(recorded, dict) or "kind" not in recorded:
        return None, "the file records no flow"
    kind = recorded["kind"]
    if kind not in FLOWS:
        return None, f"its flow {kind!r} is not one of {', '.join(FLOWS)}"
    params = {k: (tuple(v) if isinstance(v, list) else v) for k, v in recorded.items()
              if k != "kind"}
    try:
        return FLOWS[kind](**params), ""
    except (TypeError, ValueError) as exc:
        return None, f"its {kind} flow cannot be rebuilt ({exc})"


def _read_pair(path: Path) -> dict:
    """The truth of a synthetic pair file: positions A and B, displacements, dt, config."""
    import h5py

    needed = ("/truth/position_a_m", "/truth/displacement_m")
    with h5py.File(path, "r") as fh:
        missing = [k for k in needed if k not in fh]
        if missing:
            raise ComparisonError(
                f"TRUTH {str(path)!r} is a synthetic pair without its truth (no "
                f"{', '.join(missing)}): expected a pair file written by plenopiv simulate "
                "pair ... --out PAIR.h5")
        out = {"position_a": fh["/truth/position_a_m"][()],
               "displacement": fh["/truth/displacement_m"][()],
               "dt": float(fh.attrs.get("dt_s", np.nan))}
        try:
            out["config"] = json.loads(fh.attrs.get("config", "{}"))
        except (TypeError, ValueError):
            out["config"] = {}
    if out["position_a"].shape != out["displacement"].shape or out["position_a"].ndim != 2:
        raise ComparisonError(
            f"TRUTH {str(path)!r}: /truth/position_a_m {out['position_a'].shape} and "
            f"/truth/displacement_m {out['displacement'].shape}: expected two (N, 3) arrays")
    return out


def pair_truth(path, vectors) -> Truth:
    """The truth of a synthetic pair file (``plenopiv simulate pair``) at ``vectors``.

    The recorded flow when it can be rebuilt and moves the recorded particles from A to B
    (:data:`FLOW_TOLERANCE`), evaluated at the window centres (:func:`true_displacement`);
    otherwise the mean true displacement in each vector's window
    (:func:`window_mean_displacement`, which needs the field's grid and window).
    """
    from plenopiv.synthetic.flows import advect

    path = Path(path)
    rec = _read_pair(path)
    pa, disp, dt = rec["position_a"], rec["displacement"], rec["dt"]
    config = rec["config"] if isinstance(rec["config"], dict) else {}
    flow, why = _rebuild_flow(config.get("flow"))
    if flow is not None and not (np.isfinite(dt) and dt > 0):
        flow, why = None, f"its dt_s = {dt!r} is not a time > 0"
    if flow is not None and len(pa):
        moved = advect(flow, pa, dt) - pa
        err = float(np.abs(moved - disp).max())
        tol = FLOW_TOLERANCE * float(np.abs(disp).max()) + 1e-12
        if not err <= tol:
            flow, why = None, (f"the rebuilt {config['flow']['kind']} flow misses the recorded "
                               f"displacements by up to {err:.3g} m")
    if flow is not None:
        kind = config["flow"]["kind"]
        return Truth(true_displacement(vectors, flow, dt), SIMULATED_PAIR, "flow",
                     (f"truth: the {kind} flow recorded in {path.name} (rebuilt; it moves the "
                      f"{len(pa)} recorded particles from A to B), evaluated at each window "
                      "centre half-way between the exposures",))
    if vectors.grid is None or vectors.window_vox is None:
        raise ComparisonError(
            f"TRUTH {str(path)!r}: {why}, and the vectors hold no grid and window to average "
            "the true particles over: expected a vectors product written by plenopiv piv or "
            "plenopiv run")
    window_m = np.asarray(vectors.window_vox[::-1], float) * np.asarray(vectors.grid.voxel)
    mean, count = window_mean_displacement(vectors, pa + 0.5 * disp, disp, window_m)
    notes = [f"truth: the mean displacement of the true particles in each vector's window "
             f"({' x '.join(str(n) for n in vectors.window_vox)} voxels, z y x), at their "
             f"mid-points between the exposures; not the recorded flow: {why}"]
    empty = int((count == 0).sum())
    if empty:
        notes.append(f"{empty} vectors have no true particle in their window: left out")
    return Truth(mean, SIMULATED_PAIR, "window mean", tuple(notes))


def _grid_text(v) -> str:
    def axis(name):
        a = np.asarray(getattr(v, name), float) * 1e3
        return f"{name} {a[0]:.4g} to {a[-1]:.4g} mm" if a.size else f"{name} empty"

    return (f"{len(v.z)} x {len(v.y)} x {len(v.x)} vectors (nz, ny, nx), "
            + ", ".join(axis(n) for n in "xyz"))


def _same_axes(a, b) -> bool:
    for name in "xyz":
        p, q = np.asarray(getattr(a, name), float), np.asarray(getattr(b, name), float)
        if p.shape != q.shape:
            return False
        step = float(np.abs(np.diff(p)).min()) if p.size > 1 else max(abs(float(p[0])), 1e-3)
        if not np.allclose(p, q, rtol=0.0, atol=1e-6 * step):
            return False
    return True


def vectors_truth(path, vectors, *, vectors_path=None) -> Truth:
    """Another vectors product as the truth: it must hold vectors on the same grid."""
    from plenopiv.products.vectors import load_vectors

    truth = load_vectors(path)
    if not _same_axes(vectors, truth):
        raise ComparisonError(
            f"VECTORS {str(vectors_path or 'the field')!r} and TRUTH {str(path)!r} are on "
            f"different grids (VECTORS: {_grid_text(vectors)}; TRUTH: {_grid_text(truth)}): "
            "expected two vectors products on one vector grid")
    disp = np.stack([truth.u, truth.v, truth.w]).astype(float)
    return Truth(disp, "vectors", "vectors",
                 (f"truth: the valid vectors of {Path(path).name}, on the same grid",),
                 valid=np.asarray(truth.valid, bool))


def product_kind(path, role: str, expected: str) -> str:
    """The plenopiv product kind of the HDF5 file ``path``, or an error naming ``role``."""
    import h5py

    p = Path(path)
    if not p.exists():
        raise ComparisonError(f"{role} file {str(p)!r} not found: expected {expected}")
    if p.is_dir():
        raise ComparisonError(f"{role} {str(p)!r} is a folder: expected {expected}")
    try:
        with h5py.File(p, "r") as fh:
            kind = fh.attrs.get("product")
    except OSError as exc:
        raise ComparisonError(f"{role} {str(p)!r} is not an HDF5 file ({exc}): expected "
                              f"{expected}") from None
    return "" if kind is None else str(kind)


#: What each input of ``plenopiv compare`` must be, for its errors.
EXPECTED_VECTORS = "a vectors product (.h5 of plenopiv piv or plenopiv run)"
EXPECTED_TRUTH = ("a synthetic pair (plenopiv simulate pair ... --out PAIR.h5) or a vectors "
                  "product on the same grid")


def compare_products(vectors_path, truth_path, *, bands: int = 3) -> dict:
    """``plenopiv compare``: a vectors product against a synthetic pair or another product.

    Returns the comparison: ``vectors``, ``truth`` (the paths), ``truth_kind``,
    ``truth_at_vectors`` and the :func:`field_accuracy` of the vectors that are valid, finite
    and have their window inside the volume (and, for a vectors truth, are valid there too).
    """
    from plenopiv.products.vectors import load_vectors

    kind = product_kind(vectors_path, "VECTORS", EXPECTED_VECTORS)
    if kind != "vectors":
        raise ComparisonError(f"VECTORS {str(vectors_path)!r} is "
                              + (f"a plenopiv {kind} file" if kind else "not a plenopiv product")
                              + f": expected {EXPECTED_VECTORS}")
    vectors = load_vectors(vectors_path)
    if vectors.grid is None or vectors.window_vox is None:
        raise ComparisonError(
            f"VECTORS {str(vectors_path)!r} holds no voxel grid and window (attributes "
            "voxel_m, volume_origin_m, volume_shape and window_vox, or [volume] and [piv] "
            "windows in its config): expected a vectors product written by plenopiv piv or "
            "plenopiv run")
    tkind = product_kind(truth_path, "TRUTH", EXPECTED_TRUTH)
    if tkind == PAIR_PRODUCT:
        truth = pair_truth(truth_path, vectors)
    elif tkind == "vectors":
        truth = vectors_truth(truth_path, vectors, vectors_path=vectors_path)
    else:
        raise ComparisonError(f"TRUTH {str(truth_path)!r} is "
                              + (f"a plenopiv {tkind} file" if tkind else
                                 "not a plenopiv product") + f": expected {EXPECTED_TRUTH}")
    mask = np.asarray(vectors.valid, bool) & inner_vectors(vectors, vectors.grid,
                                                            vectors.window_vox)
    if truth.valid is not None:
        mask &= truth.valid
    measured = np.stack([vectors.u, vectors.v, vectors.w])
    z = np.broadcast_to(np.asarray(vectors.z, float)[:, None, None], mask.shape)
    acc = field_accuracy(measured, truth.displacement, z, vectors.grid.voxel, mask=mask,
                         bands=bands)
    notes = list(truth.notes)
    notes.append(f"vectors used: valid, finite, their {' x '.join(map(str, vectors.window_vox))}"
                 "-voxel window inside the volume" + (", valid in TRUTH too"
                                                      if truth.valid is not None else "")
                 + f": {acc['n_vectors']} of {mask.size}")
    if vectors.dt is not None:
        notes.append(f"VECTORS holds velocities (dt {vectors.dt:g} s): compared as "
                     "displacements, velocity x dt")
    return {"vectors": str(vectors_path), "truth": str(truth_path), "truth_kind": truth.kind,
            "truth_at_vectors": truth.at_vectors, **acc, "notes": notes + acc["notes"]}
