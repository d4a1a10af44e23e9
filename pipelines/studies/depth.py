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

Stage functions take cameras, grids and arrays and return arrays or dicts;
:func:`pipelines.studies.depth_report.run` runs the cases and does the I/O (JSON, Markdown, PNG
figures).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.camera.corrections import DepthCorrection
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import CameraModel, ExternalInterface, Sensor, Substrate, load_camera
from plenopiv.errors import ReconstructionError
from plenopiv.particles.settings import ParticleSettings
from plenopiv.reconstruction.build import cached_weights
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.synthetic.images import particle_image
from plenopiv.workflow.volume import reconstruct_volume

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

    The quantity that :func:`plenopiv.workflow.volume.reconstruct_volume` compares with
    ``[reconstruction] dark_tolerance`` (:mod:`plenopiv.reconstruction.sightline`): over the
    voxel's lateral sub-cells (≤ half a footprint), the smallest Σ_dark ŵ_ic / Σ_all ŵ_ic, with
    ŵ the weights scaled to a row maximum of 1 and "dark" meaning at or below
    ``pixel_threshold`` × the image's maximum on rows that touch the volume.

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
    from plenopiv.camera.resolution import footprint
    from plenopiv.lightfield import light_field
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

