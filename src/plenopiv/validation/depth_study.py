"""Depth study: thesis §5.1–5.2 (Tables 5.1, 5.2, Figs 5.2–5.4) with plenopiv's simulator.

plenopiv's ray tracer renders the images, its reconstruction locates the particles.

Geometry (thesis §5.1): the 50 mm lens at M = -1 (S_i,eff = S_o,eff = 100 mm) on a
41 × 41-lenslet patch of the Auburn sensor; one particle on the optical axis at
Z = -10 … +10 mm (1 mm steps); a volume as a user types it: x, y = ±1.5 mm and z from the
expected depths ± 2 mm rounded out to whole millimetres, with 0.125 mm voxels (one lenslet
footprint). With 41 lenslets one sits on the axis, so the voxel edges run through the lenslet
centres: every voxel straddles four lenslets (the grid the reconstruction must not depend
on). Cases:

``none``
    no refractive interface;
``external``
    water (n1 = 1.33) with l1 = 40 mm in front of the nominal focal plane (l2 = 69.92 mm of
    air); effective depth ΔS_eff = (n2/n1) Δz (thesis Eq. 4.7), corrected by n1/n2;
``plate_physical`` / ``plate_thesis``
    a plate t = 6.3 mm, n = 1.46 in front of the lenslets, with the two models of the MLA's back
    side (DESIGN.md §4). The simulator traces the plate exactly in both; the calibration is the
    exact one (:meth:`~plenopiv.calibration.model.Calibration.from_camera`, true S_i,eff).

What each back side does to depth (paraxial; Notes of :func:`expected_effective_depth`):
"physical" rays leave the glass with their air angle, the light field is exact and the
effective depth is the physical depth; "thesis" rays keep the in-glass angle θ/n down to the
sensor, so every aperture coordinate u of the light field is n times too small and the rays of
a particle at Z re-intersect, sharply, at Z' = n S_o Z / (S_o - (n - 1) Z) ≈ n Z: the thesis's
internal correction 1/n (Eq. 5.1) is the linear part of the exact inverse. The "thesis" back
side also makes the micro-images n times smaller than the light field assumes; that case is
reconstructed with the light-field aperture set to n N (:func:`micro_image_f_number`), and
once more with the default aperture as a diagnostic.

Stage functions take cameras, grids and arrays and return arrays or dicts; :func:`run` does the
I/O (JSON, Markdown, PNG figures).
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.camera import CameraModel, ExternalInterface, Sensor, Substrate, load_camera
from plenopiv.config import ParticleSettings, ReconstructionSettings
from plenopiv.corrections import DepthCorrection
from plenopiv.errors import ReconstructionError
from plenopiv.pipeline import reconstruct_volume
from plenopiv.products.files import atomic_path
from plenopiv.reconstruction.weights import cached_weights
from plenopiv.synthetic.images import particle_image
from plenopiv.volume import VolumeGrid

#: Particle extraction of this study (fixed, so that its tables stay reproducible): the
#: library's defaults when it was written.
STUDY_PARTICLES = ParticleSettings(threshold=0.1, threshold_reference="maximum",
                                   min_separation_vox=(8.0, 2.0, 2.0), box_vox=(8, 2, 2))
#: True depths of the thesis's study, metres (-10 … +10 mm in 1 mm steps).
DEPTHS = np.round(np.arange(-10, 11) * 1e-3, 12)
#: The external interface of §5.1: water, l1 = 40 mm (n1, n2, l1 in metres).
WATER = ExternalInterface(1.33, 1.0, 0.04)
#: The internal plate of §5.1: t = 6.3 mm, n = 1.46.
PLATE = Substrate(6.3e-3, 1.46)
#: Lateral half-width of the volume (as typed: 12 footprints, edges through lenslet centres),
#: voxel edge and depth margin, metres.
HALF_XY, VOXEL, MARGIN = 1.5e-3, 0.125e-3, 2.0e-3
#: Table 5.1 of the thesis: (slope, intercept mm, R²).
THESIS_TABLE_5_1 = {"none": (0.9925, 0.3675, 0.9971),
                    "external_uncorrected": (0.7563, 0.2694, 0.9975),
                    "external_corrected": (1.0059, 0.3583, 0.9975),
                    "internal_uncorrected": (1.4265, -0.3176, 0.9939),
                    "internal_corrected": (0.9770, -0.2175, 0.9939)}
#: Table 5.2 of the thesis (uncorrected internal plate, 0-10 mm): (slope, intercept mm, R²).
THESIS_TABLE_5_2 = {"behind": (1.4162, -0.4911, 0.9964), "in_front": (1.8026, 0.5211, 0.9984)}
#: Where the thesis saw its discontinuity (Fig 5.4), metres.
THESIS_DISCONTINUITY = 7e-3


# --------------------------------------------------------------------------------------------
# cameras and cases
# --------------------------------------------------------------------------------------------


def thesis_camera(base: CameraModel | None = None, *, lenslets: int = 41,
                  sensor_px: int = 700) -> CameraModel:
    """Return the Auburn optics, 50 mm lens at M = -1, on a ``lenslets``²-lenslet patch.

    No plate. ``base`` defaults to the ``auburn_50mm`` preset (S_i,eff = 100 mm, f/2.2); the
    sensor is cut to ``sensor_px``² pixels (7.4 µm), the array to ``lenslets``² lenslets
    (125 µm pitch).
    """
    a = load_camera("auburn_50mm") if base is None else base
    mla = dataclasses.replace(a.microlens_array, rows=lenslets, cols=lenslets, substrate=None)
    return a.replace(sensor=Sensor(sensor_px, sensor_px, a.sensor.pixel_pitch),
                     microlens_array=mla)


def with_plate(camera: CameraModel, back_side: str, plate: Substrate = PLATE) -> CameraModel:
    """Return ``camera`` with ``plate`` in front of its lenslets.

    ``back_side``: "physical" | "thesis"; S_i,eff (air-equivalent, Eq. 4.4) is kept.
    """
    mla = dataclasses.replace(camera.microlens_array, substrate=plate, back_side=back_side)
    return camera.replace(microlens_array=mla)


def micro_image_f_number(camera: CameraModel) -> float:
    """Return the f-number that the micro-images show, for the light field's aperture disc.

    The light field takes a micro-image radius R f̄/S_i,eff (R = f_m/2N), right when rays reach
    the lenslets at their air angle ("physical" back side). With the "thesis" back side the rays
    keep the in-glass angle, so the micro-images are n times smaller, R f̄/(n S_i,eff): the same
    disc as a lens stopped to n N. Without a plate or with the physical back side: N.
    """
    n_f = camera.main_lens.f_number
    if camera.microlens_array.back_side == "thesis" and camera.microlens_array.substrate:
        return n_f * camera.plate_index
    return n_f


@dataclass(frozen=True)
class DepthCase:
    """One optical arrangement of the study.

    Attributes
    ----------
    name : str
        Key in the results ("none", "external", "plate_physical", "plate_thesis", ...).
    label : str
        Legend text.
    camera : CameraModel
        Simulated (and calibrated) camera.
    settings : ReconstructionSettings
        MART options for this case.
    corrections : dict of str to DepthCorrection
        Named maps from effective to physical depth to report ("uncorrected" first).
    note : str
        Why the case is set up as it is.
    """

    name: str
    label: str
    camera: CameraModel
    settings: ReconstructionSettings = ReconstructionSettings()
    corrections: dict = field(default_factory=dict)
    note: str = ""


def study_cases(base: CameraModel | None = None, *, diagnostics: bool = True) -> list[DepthCase]:
    """Return the cases of thesis §5.1.

    With ``diagnostics``, also the "thesis" back side reconstructed with the default
    light-field aperture. Corrections are :meth:`DepthCorrection.for_camera` with
    ``internal="auto"`` (what the pipeline applies), and for the plate also ``"plate"`` (1/n
    whatever the back side) or ``"none"``, so that each back side is seen with and without the
    1/n of Eq. 5.1.
    """
    cam = thesis_camera(base)
    ext = cam.replace(external_interface=WATER)
    phys, thes = with_plate(cam, "physical"), with_plate(cam, "thesis")
    ident = DepthCorrection()
    # the light field itself shrinks the aperture disc by n for the "thesis" back side
    matched = ReconstructionSettings()
    cases = [
        DepthCase("none", "no interface", cam, corrections={"uncorrected": ident}),
        DepthCase("external", "external interface (water, l1 = 40 mm)", ext,
                  corrections={"uncorrected": ident,
                               "corrected": DepthCorrection.for_camera(ext)}),
        DepthCase("plate_physical", 'plate, "physical" back side', phys,
                  corrections={"uncorrected": DepthCorrection.for_camera(phys, internal="none"),
                               "corrected (1/n)": DepthCorrection.for_camera(
                                   phys, internal="plate")},
                  note="auto correction: none"),
        DepthCase("plate_thesis", 'plate, "thesis" back side', thes, settings=matched,
                  corrections={"uncorrected": DepthCorrection.for_camera(thes, internal="none"),
                               "corrected (1/n)": DepthCorrection.for_camera(thes)},
                  note=f"light field aperture f/{micro_image_f_number(thes):.3g} = n N, the "
                       "disc the micro-images show (auto correction: 1/n)"),
    ]
    if diagnostics:
        # the aperture the thesis's reconstruction assumed: the full disc, so that the outer
        # part of every micro-image disc is dark (f/(N/n) is what the light field then uses)
        cases.append(DepthCase(
            "plate_thesis_default_aperture", 'plate, "thesis" back side, full aperture', thes,
            settings=ReconstructionSettings(f_number=thes.main_lens.f_number
                                            / thes.plate_index),
            corrections={"uncorrected": DepthCorrection.for_camera(thes, internal="none"),
                         "corrected (1/n)": DepthCorrection.for_camera(thes)},
            note=f"light field aperture f/{thes.main_lens.f_number:g} (n times too large): "
                 f"the outer {1 - 1 / thes.plate_index ** 2:.0%} of every micro-image disc "
                 "is dark"))
    return cases


# --------------------------------------------------------------------------------------------
# geometry: what the reconstruction should find
# --------------------------------------------------------------------------------------------


def expected_effective_depth(camera: CameraModel, depth) -> np.ndarray:
    """Paraxial effective (reconstruction) depth of an on-axis particle at physical ``depth``.

    Parameters
    ----------
    camera : CameraModel
    depth : float or array
        Physical depth Z from the nominal focal plane, metres (+ away from the camera).

    Returns
    -------
    ndarray
        Effective depth Z', metres.

    Notes
    -----
    External interface: Z' = (n2/n1) Z (thesis Eq. 4.7). Plate with the "thesis" back side:
    the light field's aperture coordinates are u/n; the recorded rays pass through
    (u, 0) and X_f = u Z/(S_o + Z) on the focal plane, the reconstructed ones through (u/n, 0)
    and the same X_f, and meet on the axis where (S_o + Z')/S_o = (S_o + Z)/(S_o - (n - 1) Z):

        Z' = n S_o Z / (S_o - (n - 1) Z)

    (S_o = S_o,eff). With the "physical" back side, and without interfaces, Z' = Z.
    """
    z = np.asarray(depth, dtype=float)
    ext = camera.external_interface
    if ext is not None:
        z = z * ext.depth_ratio
    if camera.microlens_array.back_side == "thesis" and camera.microlens_array.substrate:
        n, so = camera.plate_index, camera.object_distance
        z = n * so * z / (so - (n - 1.0) * z)
    return z


def exact_thesis_inverse(camera: CameraModel, effective_depth) -> np.ndarray:
    """Inverse of the "thesis" back side's Z' (metres): Z = S_o Z' / (n S_o + (n - 1) Z').

    The 1/n of thesis Eq. 5.1 is its first-order term. Not a library correction: shown here to
    separate the linearisation error of Eq. 5.1 from reconstruction errors.
    """
    zp = np.asarray(effective_depth, dtype=float)
    n, so = camera.plate_index, camera.object_distance
    return so * zp / (n * so + (n - 1.0) * zp)


def image_distance_of(camera: CameraModel, depth) -> np.ndarray:
    """Air-equivalent image distance S_i(Z) = 1/(1/f_m - 1/S_o(Z)) of depth Z, metres.

    S_o(Z) = S_o,eff + effective Z (thin lens, Eq. 3.1).
    """
    z = np.asarray(depth, dtype=float)
    ext = camera.external_interface
    so = camera.object_distance + (z if ext is None else z * ext.depth_ratio)
    return 1.0 / (1.0 / camera.main_lens.focal_length - 1.0 / so)


def focus_crossing_depth(camera: CameraModel) -> float:
    """Depth Z* (metres) beyond which a particle's image forms in front of the plate.

    The image of Z converges at S_i(Z) (air). Where S_i(Z) > l3 = S_i,eff - t/n the cone
    enters the glass before it converges: it focuses inside the plate (0 < Z < Z*) or behind
    the lenslets (Z < 0). Where S_i(Z) < l3, i.e. Z > Z*, it converges in the air between the
    main lens and the plate ("in front of the plate") and enters the glass diverging.
    """
    if camera.microlens_array.substrate is None:
        raise ValueError("focus_crossing_depth: the camera has no plate in front of its lenslets")
    so_star = 1.0 / (1.0 / camera.main_lens.focal_length - 1.0 / camera.l3)
    return so_star - camera.object_distance


def focus_region(camera: CameraModel, depth) -> np.ndarray:
    """Say where the image of each depth (metres) converges.

    "behind the lenslets", "inside the plate" or "in front of the plate" (or "no plate").
    """
    z = np.atleast_1d(np.asarray(depth, dtype=float))
    if camera.microlens_array.substrate is None:
        return np.full(z.shape, "no plate", dtype=object)
    si = image_distance_of(camera, z)
    out = np.full(z.shape, "inside the plate", dtype=object)
    out[si >= camera.image_distance] = "behind the lenslets"
    out[si < camera.l3] = "in front of the plate"
    return out


def study_grid(effective_depths, *, half_xy: float = HALF_XY, voxel: float = VOXEL,
               margin: float = MARGIN) -> VolumeGrid:
    """Return the grid a user would type for ``effective_depths``.

    x, y = ±``half_xy``; z from the depths ± ``margin`` rounded out to whole millimetres;
    ``voxel`` edges. Nothing aligns the voxels with the lenslet footprints. All lengths in metres.
    """
    z = np.asarray(effective_depths, dtype=float)
    lo = np.floor((z.min() - margin) * 1e3 + 1e-9) * 1e-3
    hi = np.ceil((z.max() + margin) * 1e3 - 1e-9) * 1e-3
    return VolumeGrid.from_bounds((-half_xy, half_xy), (-half_xy, half_xy), (lo, hi),
                                  voxel=voxel)


# --------------------------------------------------------------------------------------------
# the measurement
# --------------------------------------------------------------------------------------------


def dark_fraction(weights, calibration, settings, image, voxel_index: int) -> float:
    """Return the soft line-of-sight mask's dark fraction at one voxel (best-lit sub-cell).

    The quantity that :func:`plenopiv.pipeline.reconstruct_volume` compares with
    ``[reconstruction] dark_tolerance`` (:mod:`plenopiv.reconstruction.sightline`): over the voxel's lateral
    sub-cells (≤ half a footprint), the smallest Σ_dark ŵ_ic / Σ_all ŵ_ic, with ŵ the weights
    scaled to a row maximum of 1 and "dark" meaning at or below ``pixel_threshold`` × the
    image's maximum on rows that touch the volume.

    Parameters
    ----------
    weights : Weights
    calibration : Calibration
    settings : ReconstructionSettings
    image : ndarray
        Full sensor image.
    voxel_index : int
        Flat ``[z, y, x]`` index of the voxel.
    """
    from plenopiv.lightfield import light_field
    from plenopiv.pipeline import footprint
    from plenopiv.reconstruction.sightline import subcell_line_of_sight

    _, row_scale = weights.normalised
    nonempty = weights.row_max > 0
    touching = nonempty & (row_scale >= 0.25 * float(np.percentile(row_scale[nonempty], 95)))
    raw = weights.image_vector(image)
    dark = (raw <= settings.pixel_threshold * float(np.max(image))) & touching
    _, _, best = subcell_line_of_sight(
        weights, lambda: light_field(calibration, f_number=settings.f_number,
                                     min_lit=settings.min_lit),
        dark, tolerance=settings.dark_tolerance,
        footprint=footprint(calibration.effective_camera))
    return float(best.reshape(-1)[voxel_index])


def measure_depths(case: DepthCase, depths=DEPTHS, *, rays_per_particle: int = 20000,
                   particles: ParticleSettings | None = None,
                   cache_dir: str | Path | None = None, grid: VolumeGrid | None = None,
                   margin: float = MARGIN, mask_diagnostic: bool = True) -> dict:
    """Simulate one on-axis particle per depth, reconstruct it and locate it.

    Parameters
    ----------
    case : DepthCase
    depths : array_like
        True physical depths Z, metres.
    rays_per_particle : int
        Aperture samples of the ray tracer per image.
    grid : VolumeGrid, optional
        Default: :func:`study_grid` around the case's expected effective depths, ``margin``
        (metres) to spare.
    mask_diagnostic : bool
        Also compute the soft mask's dark fraction at the expected voxel (:func:`dark_fraction`,
        ~0.1-0.5 s per depth); NaN otherwise.

    Returns
    -------
    dict
        ``depth_m``, ``effective_m`` (brightest particle's effective depth, NaN where none was
        found), ``expected_effective_m``, ``lateral_vox`` (its largest |x|, |y| in voxels),
        ``n_particles``, ``dark_fraction`` (of the voxel at the expected position),
        ``second_intensity`` (2nd brightest / brightest, 0 if one), ``errors`` (messages),
        ``grid`` (config dict) and ``seconds``.
    """
    t0 = time.perf_counter()
    particles = STUDY_PARTICLES if particles is None else particles
    depths = np.asarray(depths, dtype=float)
    cam = case.camera
    expected = expected_effective_depth(cam, depths)
    if grid is None:
        grid = study_grid(expected, margin=margin)
    cal = Calibration.from_camera(cam)
    weights, _ = cached_weights(cal, grid, cache_dir=cache_dir, f_number=case.settings.f_number,
                                min_lit=case.settings.min_lit)
    eff = np.full(len(depths), np.nan)
    lateral = np.full(len(depths), np.nan)
    second = np.zeros(len(depths))
    count = np.zeros(len(depths), int)
    dark = np.full(len(depths), np.nan)
    errors = []
    iy, ix = int(np.argmin(np.abs(grid.y))), int(np.argmin(np.abs(grid.x)))
    for i, z in enumerate(depths):
        img = particle_image(cam, [(0.0, 0.0, z)], rays_per_particle=rays_per_particle, seed=i)
        k = int(np.clip(np.rint((expected[i] - grid.origin[2]) / grid.voxel[2]), 0,
                        grid.shape[0] - 1))
        if mask_diagnostic:
            dark[i] = dark_fraction(weights, cal, case.settings, img,
                                    int(np.ravel_multi_index((k, iy, ix), grid.shape)))
        try:
            res = reconstruct_volume(cal, img, grid, settings=case.settings, particles=particles,
                                     weights=weights)
        except ReconstructionError as exc:
            errors.append(f"Z = {z * 1e3:+.1f} mm: {exc}")
            continue
        count[i] = len(res.particle_intensity)
        if count[i] == 0:
            errors.append(f"Z = {z * 1e3:+.1f} mm: no particle found")
            continue
        order = np.argsort(res.particle_intensity)[::-1]
        best = order[0]
        eff[i] = res.particle_position_effective[best, 2]
        lateral[i] = np.abs(res.particle_position_effective[best, :2]).max() / grid.voxel[0]
        if count[i] > 1:
            second[i] = res.particle_intensity[order[1]] / res.particle_intensity[best]
    return {"depth_m": depths, "effective_m": eff, "expected_effective_m": expected,
            "lateral_vox": lateral, "n_particles": count, "dark_fraction": dark,
            "second_intensity": second, "errors": errors, "grid": grid.to_dict(),
            "n_rows": int(len(weights.pixel)), "nnz": int(weights.nnz),
            "seconds": time.perf_counter() - t0}


def linear_fit(x, y) -> dict:
    """Least-squares line y = slope·x + intercept over the finite pairs (x, y in metres).

    Returns slope, ``intercept_mm``, ``r2``, ``rms_residual_mm``, ``max_abs_residual_mm`` and
    ``n``.
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if len(x) < 2:
        return {"slope": np.nan, "intercept_mm": np.nan, "r2": np.nan, "rms_residual_mm": np.nan,
                "max_abs_residual_mm": np.nan, "n": int(len(x))}
    slope, icpt = np.polyfit(x, y, 1)
    res = y - (slope * x + icpt)
    ss_tot = float(((y - y.mean()) ** 2).sum())
    return {"slope": float(slope), "intercept_mm": float(icpt * 1e3),
            "r2": 1.0 - float((res ** 2).sum()) / ss_tot if ss_tot > 0 else np.nan,
            "rms_residual_mm": float(np.sqrt(np.mean(res ** 2)) * 1e3),
            "max_abs_residual_mm": float(np.abs(res).max() * 1e3), "n": int(len(x))}


def corrected_depths(case: DepthCase, measured: dict) -> dict:
    """Each named correction of ``case`` applied to the measured effective depths (metres)."""
    return {name: corr.depth(measured["effective_m"]) for name, corr in case.corrections.items()}


# --------------------------------------------------------------------------------------------
# tables
# --------------------------------------------------------------------------------------------


def _thesis_key(case: str, corr: str, fit_range: str) -> str | None:
    if case == "none" and fit_range == "±10 mm":
        return "none"
    if case == "external" and fit_range == "±10 mm":
        return "external_" + corr.split(" ")[0]
    if case == "plate_thesis" and fit_range == "±5 mm" and corr in ("uncorrected",
                                                                     "corrected (1/n)"):
        return "internal_" + corr.split(" ")[0]
    return None


def table_5_1(cases: list[DepthCase], measured: dict) -> list[dict]:
    """Fit reconstructed against true depth, per case and correction (thesis Table 5.1).

    Slope, intercept and R² over ±10 mm, and for the plate also over ±5 mm (the range of the
    thesis's internal fits, Fig 5.3), next to the thesis's numbers where it gives them.
    """
    rows = []
    for case in cases:
        m = measured[case.name]
        z = m["depth_m"]
        ranges = {"±10 mm": np.abs(z) <= 10.0e-3 + 1e-12}
        if case.camera.microlens_array.substrate is not None:
            ranges["±5 mm"] = np.abs(z) <= 5.0e-3 + 1e-12
        named = corrected_depths(case, m)
        if case.name.startswith("plate_thesis"):
            named["exact inverse of u/n (not in the library)"] = exact_thesis_inverse(
                case.camera, m["effective_m"])
        for corr, zc in named.items():
            for rname, sel in ranges.items():
                fit = linear_fit(z[sel], zc[sel])
                key = _thesis_key(case.name, corr, rname)
                rows.append({"case": case.name, "label": case.label, "correction": corr,
                             "fit_range": rname, **fit,
                             "thesis": None if key is None else dict(zip(
                                 ("slope", "intercept_mm", "r2"), THESIS_TABLE_5_1[key],
                                 strict=True))})
    return rows


def table_5_2(cases: list[DepthCase], measured: dict) -> list[dict]:
    """Fit the plate's 0-10 mm either side of the focus crossing (thesis Table 5.2).

    Uncorrected depths; separate fits for particles whose image converges
    behind the plate's front face (in the glass or behind the lenslets) and in front of it, split
    at the geometric Z* (:func:`focus_crossing_depth`) and, for comparison, at the thesis's
    7 mm. ``jump_mm`` is the difference of the two lines at the split; ``expected_jump_mm`` the
    same for the paraxial prediction (curvature alone, no discontinuity);
    ``residual_step_mm`` the mean residual from the prediction in front minus behind. The case
    without interface, split at the same depths, is the control (thesis Table 5.2's first
    column): whatever it shows is not the plate's doing.
    """
    plates = [c for c in cases if c.camera.microlens_array.substrate is not None]
    if not plates:
        return []
    zstar = focus_crossing_depth(plates[0].camera)
    rows = []
    for case in cases:
        if case.camera.microlens_array.substrate is None and case.name != "none":
            continue
        m = measured[case.name]
        z, ze, pred = m["depth_m"], m["effective_m"], m["expected_effective_m"]
        for split_name, split in (("geometric Z*", zstar), ("thesis 7 mm", THESIS_DISCONTINUITY)):
            behind = (z >= -1e-12) & (z <= split)
            front = (z > split) & (z <= 10e-3 + 1e-12)
            fb, ff = linear_fit(z[behind], ze[behind]), linear_fit(z[front], ze[front])
            pb, pf = linear_fit(z[behind], pred[behind]), linear_fit(z[front], pred[front])

            def at(fit, x=split):
                return fit["slope"] * x * 1e3 + fit["intercept_mm"]

            res = (ze - pred) * 1e3
            rows.append({
                "case": case.name, "label": case.label, "split": split_name,
                "split_mm": split * 1e3, "behind": fb, "in_front": ff,
                "expected_behind": pb, "expected_in_front": pf,
                "jump_mm": at(ff) - at(fb), "expected_jump_mm": at(pf) - at(pb),
                "residual_step_mm": float(np.nanmean(res[front]) - np.nanmean(res[behind])),
                "residual_sd_mm": float(np.nanstd(res[behind | front])),
                "thesis": {k: dict(zip(("slope", "intercept_mm", "r2"), v, strict=True))
                           for k, v in THESIS_TABLE_5_2.items()}})
    return rows


# --------------------------------------------------------------------------------------------
# figures and report
# --------------------------------------------------------------------------------------------


def _savefig(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)


def _plot(cases: list[DepthCase], measured: dict, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    by = {c.name: c for c in cases}
    paths = []
    style = {"none": ("tab:blue", "o"), "external": ("tab:red", "s"),
             "plate_thesis": ("tab:green", "^"), "plate_physical": ("tab:purple", "D"),
             "plate_thesis_default_aperture": ("tab:olive", "v")}

    def panel(ax, names, corr_of, lim, title):
        ax.plot([-lim, lim], [-lim, lim], "k-", lw=1, label="ideal")
        for name in names:
            if name not in measured:
                continue
            m, c = measured[name], by[name]
            z = m["depth_m"]
            sel = np.abs(z) <= lim * 1e-3 + 1e-12
            corr = corr_of(c)
            zc = c.corrections[corr].depth(m["effective_m"])
            fit = linear_fit(z[sel], zc[sel])
            col, mk = style.get(name, ("k", "x"))
            ax.plot(z[sel] * 1e3, zc[sel] * 1e3, mk, color=col, ms=5,
                    label=f"{c.label}: slope {fit['slope']:.4f}")
            xx = np.array([-lim, lim])
            ax.plot(xx, fit["slope"] * xx + fit["intercept_mm"], "-", color=col, lw=0.8)
        ax.set_xlabel("true depth Z (mm)")
        ax.set_ylabel("reconstructed depth (mm)")
        ax.set_title(title)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")

    def corrected(c):
        return "corrected" if "corrected" in c.corrections else (
            "corrected (1/n)" if c.name.startswith("plate_thesis") else "uncorrected")

    fig, ax = plt.subplots(1, 2, figsize=(11, 4.8), sharey=True)
    panel(ax[0], ("none", "external"), lambda c: "uncorrected", 10,
          "(a) uncorrected (effective depth)")
    panel(ax[1], ("none", "external"), corrected, 10, "(b) corrected, Z = (n1/n2) ΔS_eff (Eq. 4.7)")
    fig.suptitle("Fig 5.2: external interface (water, n1 = 1.33, l1 = 40 mm), 50 mm lens, M = -1")
    paths.append(out / "fig_5_2_external.png")
    _savefig(fig, paths[-1])

    fig, ax = plt.subplots(1, 2, figsize=(11, 4.8), sharey=True)
    names = ("none", "plate_thesis", "plate_physical")
    panel(ax[0], names, lambda c: "uncorrected", 5, "(a) uncorrected (effective depth)")
    panel(ax[1], names, corrected, 5,
          '(b) corrected: "thesis" ÷ n (Eq. 5.1), "physical" none (auto)')
    fig.suptitle("Fig 5.3: plate t = 6.3 mm, n = 1.46 in front of the lenslets, ±5 mm")
    paths.append(out / "fig_5_3_internal.png")
    _savefig(fig, paths[-1])

    fig, ax = plt.subplots(1, 2, figsize=(11, 4.8))
    zstar = None
    for name in ("plate_thesis", "plate_physical"):
        if name not in measured:
            continue
        m, c = measured[name], by[name]
        zstar = focus_crossing_depth(c.camera)
        z = m["depth_m"]
        sel = (z >= -1e-12) & (z <= 10e-3 + 1e-12)
        col, mk = style[name]
        ax[0].plot(z[sel] * 1e3, m["effective_m"][sel] * 1e3, mk, color=col, ms=5,
                   label=f"{c.label}")
        zz = np.linspace(0, 10e-3, 101)
        ax[0].plot(zz * 1e3, expected_effective_depth(c.camera, zz) * 1e3, ":", color=col,
                   lw=1, label="paraxial prediction")
        for part in (z[sel] <= zstar, z[sel] > zstar):
            fit = linear_fit(z[sel][part], m["effective_m"][sel][part])
            xx = z[sel][part] * 1e3
            ax[0].plot(xx, fit["slope"] * xx + fit["intercept_mm"], "-", color=col, lw=0.8)
        ax[1].plot(z[sel] * 1e3, (m["effective_m"][sel] - m["expected_effective_m"][sel]) * 1e3,
                   mk + "-", color=col, ms=5, lw=0.8, label=c.label)
    if "none" in measured:
        m = measured["none"]
        z = m["depth_m"]
        sel = (z >= -1e-12) & (z <= 10e-3 + 1e-12)
        col, mk = style["none"]
        ax[1].plot(z[sel] * 1e3, (m["effective_m"][sel] - m["expected_effective_m"][sel]) * 1e3,
                   mk + "--", color=col, ms=4, lw=0.8, alpha=0.8, label="no interface (control)")
    (sb, ib, _), (sf, i_f, _) = THESIS_TABLE_5_2["behind"], THESIS_TABLE_5_2["in_front"]
    xb, xf = np.array([0.0, 7.0]), np.array([7.0, 10.0])
    ax[0].plot(xb, sb * xb + ib, "--", color="tab:orange", lw=1.2,
               label="thesis Table 5.2 fits (ALFA)")
    ax[0].plot(xf, sf * xf + i_f, "--", color="tab:orange", lw=1.2)
    ax[0].plot([0, 10], [0, 10], "k-", lw=1, label="ideal")
    for a in ax:
        if zstar is not None:
            a.axvline(zstar * 1e3, color="0.4", ls="--", lw=1)
        a.axvline(THESIS_DISCONTINUITY * 1e3, color="tab:orange", ls="-.", lw=1)
        a.set_xlabel("true depth Z (mm)")
        a.grid(alpha=0.3)
    ax[1].axhspan(-VOXEL * 1e3, VOXEL * 1e3, color="0.85", zorder=0, label="± 1 voxel")
    ax[0].set_ylabel("reconstructed (effective) depth (mm)")
    ax[1].set_ylabel("reconstructed − paraxial prediction (mm)")
    ax[0].set_title("(a) uncorrected; lines: fits either side of Z*")
    ax[1].set_title(f"(b) residual; dashed: Z* = {zstar * 1e3:.2f} mm, dash-dot: thesis's 7 mm"
                    if zstar is not None else "(b) residual")
    ax[0].legend(fontsize=7, loc="upper left")
    ax[1].legend(fontsize=7)
    fig.suptitle("Fig 5.4: plate, 0-10 mm: focus behind (Z < Z*) or in front of (Z > Z*) the "
                 "plate's front face")
    paths.append(out / "fig_5_4_internal_focus.png")
    _savefig(fig, paths[-1])
    return paths


def _fmt(v, spec):
    return "–" if v is None or not np.isfinite(v) else format(v, spec)


def _fit(results: dict, case: str, correction: str, fit_range: str = "±10 mm") -> dict:
    for r in results["table_5_1"]:
        if (r["case"], r["correction"], r["fit_range"]) == (case, correction, fit_range):
            return r
    return {"slope": np.nan, "intercept_mm": np.nan, "rms_residual_mm": np.nan}


def _summary(results: dict) -> list[str]:
    """Put the findings in words, every number taken from ``results``."""
    f, meas = _fit, results["measured"]
    rec = results["cases"]["none"]["reconstruction"]
    out = ["## Summary", ""]
    out.append(f"- No interface: slope {f(results, 'none', 'uncorrected')['slope']:.4f} "
               "(thesis 0.9925).")
    if "external" in meas:
        out.append(
            f"- External window: uncorrected {f(results, 'external', 'uncorrected')['slope']:.4f}"
            f" (n2/n1 = {1 / 1.33:.4f}; thesis 0.7563), corrected by n1/n2 "
            f"{f(results, 'external', 'corrected')['slope']:.4f} (thesis 1.0059).")
    if "plate_physical" in meas:
        out.append(
            '- Plate, "physical" back side: uncorrected '
            f"{f(results, 'plate_physical', 'uncorrected')['slope']:.4f}; S_i,eff accounts for "
            "the plate and the light field is exact, so no correction is needed (the 1/n of "
            f"Eq. 5.1 would give {f(results, 'plate_physical', 'corrected (1/n)')['slope']:.4f}).")
    if "plate_thesis" in meas:
        u10, u5 = (f(results, "plate_thesis", "uncorrected", r) for r in ("±10 mm", "±5 mm"))
        c10, c5 = (f(results, "plate_thesis", "corrected (1/n)", r) for r in ("±10 mm", "±5 mm"))
        ex = f(results, "plate_thesis", "exact inverse of u/n (not in the library)")
        out.append(
            f'- Plate, "thesis" back side: uncorrected {u10["slope"]:.4f} over ±10 mm, '
            f'{u5["slope"]:.4f} over ±5 mm (thesis 1.4265); after the 1/n of Eq. 5.1 '
            f'{c10["slope"]:.4f} and {c5["slope"]:.4f} (thesis 0.9770). The 1/n is the '
            "linear part of Z' = n S_o Z/(S_o - (n-1) Z): the corrected fit over ±10 mm keeps an "
            f'intercept of {c10["intercept_mm"]:+.3f} mm and an rms residual of '
            f'{c10["rms_residual_mm"]:.3f} mm, against {ex["intercept_mm"]:+.3f} mm and '
            f'{ex["rms_residual_mm"]:.3f} mm through the exact inverse.')
    if "plate_thesis_default_aperture" in meas:
        m = meas["plate_thesis_default_aperture"]
        d = np.asarray(m["dark_fraction"], float)
        split = int(np.sum(np.asarray(m["n_particles"]) > 1))
        out.append(
            '- The "thesis" back side with the default light-field aperture: the micro-images '
            "are n times smaller than the light field assumes, so at the particle's own voxel "
            f"{np.nanmin(d):.2f}-{np.nanmax(d):.2f} of the weight falls on dark pixels, against "
            f"the soft mask's `dark_tolerance` = {rec['dark_tolerance']:g} (with the matched "
            "aperture: "
            f"{np.nanmin(meas['plate_thesis']['dark_fraction']):.3f}-"
            f"{np.nanmax(meas['plate_thesis']['dark_fraction']):.3f}); {split} of "
            f"{len(d)} depths give a second particle, and the uncorrected slope is "
            f"{f(results, 'plate_thesis_default_aperture', 'uncorrected')['slope']:.4f}.")
    for r in results["table_5_2"]:
        if r["split"] != "geometric Z*":
            continue
        out.append(f"- Table 5.2, {r['label']}: the two fits differ by {r['jump_mm']:+.3f} mm at "
                   f"Z* = {r['split_mm']:.2f} mm (paraxial curvature alone: "
                   f"{r['expected_jump_mm']:+.3f} mm).")
    out.append("- The no-interface rows of Table 5.2 are the control: the same split without a "
               "plate shows what the scatter of single depths near the focal plane does alone.")
    t = THESIS_TABLE_5_2
    out.append("- The thesis's fits differ by "
               f"{(t['in_front'][0] - t['behind'][0]) * 7 + t['in_front'][1] - t['behind'][1]:+.2f}"
               " mm at 7 mm.")
    worst = []
    for name, m in meas.items():
        e = np.abs(np.asarray(m["effective_m"], float) - np.asarray(m["expected_effective_m"]))
        if np.all(np.isnan(e)):
            continue
        i = int(np.nanargmax(e))
        worst.append(f"{results['cases'][name]['label']}: {e[i] * 1e3:.2f} mm at "
                     f"Z = {m['depth_m'][i] * 1e3:+.0f} mm (effective "
                     f"{m['expected_effective_m'][i] * 1e3:+.2f} mm)")
    out.append("- Largest single-depth errors (against the paraxial expectation): "
               + "; ".join(worst) + ".")
    return out + [""]


def _markdown(results: dict) -> str:
    geo = results["geometry"]
    rec = results["cases"]["none"]["reconstruction"]
    lines = [
        "# Depth study (thesis §5.1-5.2): Table 5.1, Table 5.2, Figs 5.2-5.4", "",
        "Generated by `python pipelines/validate_depth.py` (`plenopiv validate depth`). One "
        "particle on the optical axis at Z = -10 … +10 mm (1 mm steps), rendered by plenopiv's ray "
        f"tracer ({results['rays_per_particle']} rays, exact refraction at the window and the "
        "plate), reconstructed by `pipeline.reconstruct_volume` (MLOS + soft line-of-sight mask + "
        f"{rec['method']}, {rec['iterations']} iterations, pixel_threshold "
        f"{rec['pixel_threshold']:g}, dark_tolerance {rec['dark_tolerance']:g}; the library's "
        "defaults except where a case says otherwise) with the exact calibration "
        "(`Calibration.from_camera`: the true S_i,eff), located by the brightest particle's "
        "centroid.", "",
        f"Camera: 50 mm lens, f/{geo['f_number']:g}, S_i,eff = S_o,eff = "
        f"{geo['si_eff_mm']:.2f} mm (M = -1), {geo['lenslets']} × {geo['lenslets']} lenslets of "
        "the Auburn MLA (125 µm, f̄ = 500 µm, 7.4 µm pixels). Volume as a user types it: x, y = "
        f"±{HALF_XY * 1e3:g} mm, 0.125 mm voxels whose edges run through the lenslet centres "
        "(every voxel straddles four lenslets; nothing aligns the grid with the footprints); "
        "each case's depth range covers its expected effective depths with "
        f"{MARGIN * 1e3:g} mm to spare, rounded out to whole millimetres (table below). "
        "External interface: "
        f"n1 = 1.33, l1 = 40 mm, l2 = {geo['l2_mm']:.2f} mm. Plate: t = 6.3 mm, n = 1.46, "
        f"l3 = {geo['l3_mm']:.2f} mm.", "", *_summary(results),
        "## Table 5.1: reconstructed against true depth", "",
        "| case | correction | fit range | slope | intercept (mm) | R² | rms residual (mm) | "
        "thesis slope | thesis intercept (mm) | thesis R² |",
        "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results["table_5_1"]:
        t = r["thesis"] or {}
        lines.append(
            f"| {r['label']} | {r['correction']} | {r['fit_range']} | {_fmt(r['slope'], '.4f')} | "
            f"{_fmt(r['intercept_mm'], '.4f')} | {_fmt(r['r2'], '.5f')} | "
            f"{_fmt(r['rms_residual_mm'], '.3f')} | {_fmt(t.get('slope'), '.4f')} | "
            f"{_fmt(t.get('intercept_mm'), '.4f')} | {_fmt(t.get('r2'), '.4f')} |")
    lines += ["", "## Table 5.2: plate, 0-10 mm, uncorrected; fits either side of the focus "
              "crossing", "",
              "The image of depth Z converges at S_i(Z) = 1/(1/f - 1/(S_o,eff + Z)); it reaches "
              f"the plate's front face (l3 = {geo['l3_mm']:.3f} mm) at Z* = "
              f"{geo['z_star_mm']:.3f} mm. "
              "For Z < 0 the image forms behind the lenslets, for 0 < Z < Z* inside the glass, for "
              "Z > Z* in the air in front of the plate (between lens and plate). The thesis saw a "
              "jump near 7 mm; Z = 7 mm images at S_i = "
              f"{geo['si_at_7mm_mm']:.2f} mm, which is S_i,eff - t = "
              f"{geo['si_eff_mm'] - 6.3:.2f} mm (a plate whose front face lies t, not t/n, before "
              "the effective lenslet plane) to within "
              f"{abs(geo['si_at_7mm_mm'] - geo['si_eff_mm'] + 6.3):.2f} mm.", "",
              "| case | split at (mm) | behind: slope | intercept (mm) | R² | in front: slope | "
              "intercept (mm) | R² | jump at split (mm) | expected jump, paraxial (mm) | "
              "step in residual (mm) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results["table_5_2"]:
        b, f = r["behind"], r["in_front"]
        lines.append(
            f"| {r['label']} | {r['split_mm']:.2f} ({r['split']}) | {_fmt(b['slope'], '.4f')} | "
            f"{_fmt(b['intercept_mm'], '.4f')} | {_fmt(b['r2'], '.5f')} | "
            f"{_fmt(f['slope'], '.4f')} | {_fmt(f['intercept_mm'], '.4f')} | "
            f"{_fmt(f['r2'], '.5f')} | {_fmt(r['jump_mm'], '+.3f')} | "
            f"{_fmt(r['expected_jump_mm'], '+.3f')} | {_fmt(r['residual_step_mm'], '+.3f')} |")
    t = THESIS_TABLE_5_2
    lines += [f"| thesis (ALFA) | ≈ 7 | {t['behind'][0]} | {t['behind'][1]} | {t['behind'][2]} | "
              f"{t['in_front'][0]} | {t['in_front'][1]} | {t['in_front'][2]} | "
              f"{(t['in_front'][0] - t['behind'][0]) * 7 + t['in_front'][1] - t['behind'][1]:+.3f}"
              " | | |", ""]
    lines += ["## Per-depth measurements", "",
              "Effective depth of the brightest particle, the paraxial expectation, the number of "
              "particles found (and the 2nd brightest's intensity relative to the 1st), the "
              "largest lateral offset (voxels) and the dark fraction of the soft mask at the "
              "expected voxel, that of its best-lit sub-cell (`plenopiv.reconstruction.sightline`; the mask "
              f"empties a voxel above `dark_tolerance` = {rec['dark_tolerance']:g}).", ""]
    for name, m in results["measured"].items():
        c = results["cases"][name]
        lines += [f"### {c['label']}", "", f"{c['note']}" if c["note"] else "",
                  f"Grid z = {m['grid']['z_mm'][0]:.3f} … {m['grid']['z_mm'][1]:.3f} mm, shape "
                  f"{m['grid']['shape']}; {m['seconds']:.0f} s.", "",
                  "| Z (mm) | effective (mm) | expected (mm) | error (mm) | particles | 2nd/1st "
                  "| lateral (vox) | dark fraction |", "|---|---|---|---|---|---|---|---|"]
        for i, z in enumerate(m["depth_m"]):
            e, p = m["effective_m"][i], m["expected_effective_m"][i]
            lines.append(f"| {z * 1e3:+.0f} | {_fmt(e * 1e3, '+.3f')} | {p * 1e3:+.3f} | "
                         f"{_fmt((e - p) * 1e3, '+.3f')} | {m['n_particles'][i]} | "
                         f"{m['second_intensity'][i]:.2f} | {_fmt(m['lateral_vox'][i], '.2f')} | "
                         f"{_fmt(m['dark_fraction'][i], '.3f')} |")
        for err in m["errors"]:
            lines.append(f"\n- {err}")
        lines.append("")
    lines += ["## Figures", ""] + [f"- `{Path(p).name}`" for p in results["figures"]]
    return "\n".join(lines) + "\n"


def _jsonable(obj):
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return _jsonable(obj.item())
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def run(out: str | Path, *, depths=DEPTHS, rays_per_particle: int = 20000,
        diagnostics: bool = True, cache_dir: str | Path | None = None,
        progress=None) -> dict:
    """Run the depth study; write JSON, Markdown and Figs 5.2-5.4 (PNG) to ``out``.

    Files: ``depth_study.json``, ``depth_study.md``, ``fig_5_2_external.png``,
    ``fig_5_3_internal.png``, ``fig_5_4_internal_focus.png``.

    Parameters
    ----------
    out : path
        Output folder (created).
    depths : array_like
        True depths, metres (default -10 … +10 mm in 1 mm steps).
    rays_per_particle : int
        Ray-tracer samples per image.
    diagnostics : bool
        Also run the "thesis" back side with the default light-field aperture.
    cache_dir : path, optional
        Weight cache folder (default: none, weights built in memory).
    progress : callable, optional
        ``progress(case_name, seconds)`` after each case.

    Returns
    -------
    dict
        A summary: output paths, the slopes per case and correction (±10 mm), Z* and seconds.
    """
    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cases = study_cases(diagnostics=diagnostics)
    measured = {}
    for case in cases:
        measured[case.name] = measure_depths(case, depths, rays_per_particle=rays_per_particle,
                                             cache_dir=cache_dir)
        if progress is not None:
            progress(case.name, measured[case.name]["seconds"])
    by = {c.name: c for c in cases}
    plate = by["plate_thesis"].camera
    cam0 = by["none"].camera
    geometry = {"f_number": cam0.main_lens.f_number, "si_eff_mm": cam0.image_distance * 1e3,
                "so_eff_mm": cam0.object_distance * 1e3,
                "lenslets": cam0.microlens_array.rows,
                "l2_mm": by["external"].camera.interface_distance * 1e3,
                "l3_mm": plate.l3 * 1e3, "z_star_mm": focus_crossing_depth(plate) * 1e3,
                "si_at_7mm_mm": float(image_distance_of(plate, THESIS_DISCONTINUITY)) * 1e3,
                "focus_region": dict(zip((np.asarray(depths) * 1e3).round(3).tolist(),
                                         focus_region(plate, depths).tolist(), strict=True))}
    results = {
        "study": "thesis §5.1-5.2 depth study", "rays_per_particle": rays_per_particle,
        "geometry": geometry,
        "cases": {c.name: {"label": c.label, "note": c.note, "camera": c.camera.to_dict(),
                           "reconstruction": c.settings.model_dump(),
                           "particles": STUDY_PARTICLES.model_dump(),
                           "corrections": {k: v.to_dict() for k, v in c.corrections.items()}}
                  for c in cases},
        "measured": measured,
        "table_5_1": table_5_1(cases, measured),
        "table_5_2": table_5_2(cases, measured),
    }
    results["figures"] = [str(p) for p in _plot(cases, measured, out)]
    results["seconds"] = time.perf_counter() - t0
    with atomic_path(out / "depth_study.json") as tmp:
        tmp.write_text(json.dumps(_jsonable(results), indent=1))
    with atomic_path(out / "depth_study.md") as tmp:
        tmp.write_text(_markdown(results))
    slopes = {f"{r['case']} {r['correction']}": round(r["slope"], 4)
              for r in results["table_5_1"] if r["fit_range"] == "±10 mm"}
    return {"out": str(out), "figures": results["figures"],
            "json": str(out / "depth_study.json"), "markdown": str(out / "depth_study.md"),
            "slopes_10mm": slopes, "z_star_mm": round(geometry["z_star_mm"], 4),
            "errors": {k: v["errors"] for k, v in measured.items() if v["errors"]},
            "seconds": round(results["seconds"], 1)}
