"""The tracks product: HDF5 (docs/design.md §7), a ``.vtp`` for ParaView, the binned field.

``TRACKS.h5``: ``/position_a_m``, ``/position_b_m``, ``/displacement_m`` (N, 3: x, y, z,
metres, depth corrections applied), ``/velocity_m_s`` when ``dt`` is known, ``/uncertainty_m``
(of the displacement), ``/uncertainty_a_m``, ``/uncertainty_b_m`` (of the positions),
``/quality`` (match uniqueness 1 - d1/d2: 1 unique, 0 ambiguous), ``/residual_cells`` (distance
of B from its PIV prediction, resolution cells), ``/index_a``, ``/index_b`` (rows of the
volumes' particle tables), ``/n_lenslets_a``, ``/n_lenslets_b`` (lenslets that fixed each
position; 1: in focus, lateral position known to a footprint only); attributes ``n_tracks``,
``dt_s`` (NaN if unknown), the matching's counts, the resolved config. ``TRACKS.vtp``: VTK XML
PolyData, one line A -> B per track. ``TRACKS_binned.h5``: the tracks averaged on the PIV grid
in the vectors product's schema (``snr`` holds the number of tracks per cell).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from plenopiv.errors import ReconstructionError
from plenopiv.products.files import atomic_path
from plenopiv.products.hdf5 import open_product, write_h5
from plenopiv.tracking.tracks import TrackResult

__all__ = ["TRACK_DATASETS", "load_tracks", "write_tracks", "write_vtp"]

#: The datasets every tracks product holds (``/velocity_m_s`` too when dt is known).
TRACK_DATASETS = ("/position_a_m", "/position_b_m", "/displacement_m", "/uncertainty_m",
                  "/uncertainty_a_m", "/uncertainty_b_m", "/quality", "/residual_cells",
                  "/index_a", "/index_b", "/n_lenslets_a", "/n_lenslets_b")


def write_tracks(path: str | Path, tracks: TrackResult, *, config: dict | None = None,
                 vtk: bool = True, extra_attrs: dict | None = None,
                 provenance: dict | None = None) -> list[Path]:
    """Write the tracks product atomically (and a ``.vtp`` beside it when ``vtk``).

    ``provenance``: what made it (:func:`~plenopiv.products.provenance.make_provenance`).
    """
    ds = {"/position_a_m": tracks.position_a, "/position_b_m": tracks.position_b,
          "/displacement_m": tracks.displacement, "/uncertainty_m": tracks.uncertainty,
          "/uncertainty_a_m": tracks.uncertainty_a, "/uncertainty_b_m": tracks.uncertainty_b,
          "/quality": tracks.quality, "/residual_cells": tracks.residual_cells,
          "/index_a": tracks.index_a.astype(np.int64),
          "/index_b": tracks.index_b.astype(np.int64),
          "/n_lenslets_a": tracks.n_lenslets_a.astype(np.int64),
          "/n_lenslets_b": tracks.n_lenslets_b.astype(np.int64)}
    units = {k: "m" for k in ds if k.endswith("_m")}
    units.update({k: "1" for k in ("/quality", "/residual_cells", "/index_a", "/index_b",
                                   "/n_lenslets_a", "/n_lenslets_b")})
    if tracks.dt is not None:
        ds["/velocity_m_s"] = tracks.velocity
        units["/velocity_m_s"] = "m s-1"
    attrs = {"n_tracks": len(tracks), "dt_s": np.nan if tracks.dt is None else tracks.dt,
             "axes": "x, y, z", **{f"count_{k}": v for k, v in tracks.counts.items()},
             **(extra_attrs or {})}
    p = write_h5(path, {k: v if v.dtype == np.int64 else np.asarray(v, float)
                        for k, v in ds.items()}, attrs=attrs, units=units, config=config,
                 kind="tracks", provenance=provenance)
    out = [p]
    if vtk:
        out.append(write_vtp(Path(path).with_suffix(".vtp"), tracks))
    return out


def load_tracks(path: str | Path) -> TrackResult:
    """Read a tracks product written by :func:`write_tracks`; every array checked finite.

    The velocity is not read (it is the displacement over ``dt``), but checked all the same.
    """
    with open_product(path, "tracks", ReconstructionError) as fh:
        a = {name: fh.array(name) for name in TRACK_DATASETS + ("/velocity_m_s",)
             if name in fh}
        dt = fh.number("dt_s", allow_nan=True)
        counts = {k[len("count_"):]: int(v) for k, v in fh.attrs.items()
                  if k.startswith("count_")}
    return TrackResult(a["/position_a_m"], a["/position_b_m"], a["/uncertainty_a_m"],
                       a["/uncertainty_b_m"], a["/quality"], a["/residual_cells"],
                       a["/index_a"], a["/index_b"], a["/n_lenslets_a"], a["/n_lenslets_b"],
                       dt if np.isfinite(dt) else None, counts)


def _data_array(name: str, values: np.ndarray) -> str:
    a = np.asarray(values, np.float64)
    ncomp = 1 if a.ndim == 1 else a.shape[1]
    body = " ".join(f"{v:.9g}" for v in a.ravel())
    return (f'<DataArray type="Float64" Name="{name}" NumberOfComponents="{ncomp}" '
            f'format="ascii">{body}</DataArray>')


def write_vtp(path: str | Path, tracks: TrackResult) -> Path:
    """Write the tracks as VTK XML PolyData lines A -> B (ParaView), atomically.

    Points are ``A_0, B_0, A_1, B_1, ...`` (metres); point data ``displacement`` (m),
    ``velocity`` (m/s, when dt is known), ``uncertainty`` (m), ``quality``.
    """
    n = len(tracks)
    pts = np.empty((2 * n, 3))
    pts[0::2], pts[1::2] = tracks.position_a, tracks.position_b

    def twice(a):
        return np.repeat(np.asarray(a, float), 2, axis=0)

    data = [_data_array("displacement", twice(tracks.displacement)),
            _data_array("uncertainty", twice(tracks.uncertainty)),
            _data_array("quality", twice(tracks.quality))]
    if tracks.dt is not None:
        data.append(_data_array("velocity", twice(tracks.velocity)))
    conn = " ".join(str(i) for i in range(2 * n))
    offs = " ".join(str(2 * (i + 1)) for i in range(n))
    xml = (
        '<?xml version="1.0"?>\n'
        '<VTKFile type="PolyData" version="0.1" byte_order="LittleEndian">\n<PolyData>\n'
        f'<Piece NumberOfPoints="{2 * n}" NumberOfVerts="0" NumberOfLines="{n}" '
        'NumberOfStrips="0" NumberOfPolys="0">\n'
        f'<PointData Vectors="displacement">\n{chr(10).join(data)}\n</PointData>\n'
        f'<Points>{_data_array("points", pts)}</Points>\n'
        '<Lines>\n'
        f'<DataArray type="Int64" Name="connectivity" format="ascii">{conn}</DataArray>\n'
        f'<DataArray type="Int64" Name="offsets" format="ascii">{offs}</DataArray>\n'
        '</Lines>\n</Piece>\n</PolyData>\n</VTKFile>\n')
    final = Path(path)
    with atomic_path(final) as tmp:
        tmp.write_text(xml)
    return final


def save_track_products(tracks: TrackResult, vectors, out: str | Path, *,
                        config: dict | None = None, vtk: bool = True,
                        extra_attrs: dict | None = None, provenance: dict | None = None) -> dict:
    """Write ``OUT`` (tracks), ``OUT.vtp`` and ``OUT_binned.h5`` (+ ``.vti``); their paths.

    The binned field records the tracks' ``provenance`` as its own (a vectors product made
    from the same inputs).
    """
    from plenopiv.tracking.tracks import bin_tracks

    out = Path(out)
    files = write_tracks(out, tracks, config=config, vtk=vtk, extra_attrs=extra_attrs,
                         provenance=provenance)
    paths = {"tracks": str(files[0])}
    if vtk:
        paths["vtp"] = str(files[1])
    binned = bin_tracks(tracks, vectors)
    bfiles = binned.save(out.with_name(out.stem + "_binned.h5"), config=config, vtk=vtk,
                         extra_attrs={"source": "particle tracks binned on the PIV grid",
                                      "snr_meaning": "tracks per cell", **(extra_attrs or {})},
                         provenance=None if provenance is None else {**provenance,
                                                                      "product": "vectors"})
    paths["binned"] = str(bfiles[0])
    return paths
