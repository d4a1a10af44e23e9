"""``plenopiv plan`` and plenopiv.workflow.planning: resolution, recommendations, fit, size and
cost."""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib

import numpy as np
import pytest

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid, volume_from_dict
from plenopiv.camera.model import load_camera
from plenopiv.camera.resolution import footprint
from plenopiv.cli import main
from plenopiv.lightfield import light_field
from plenopiv.piv.settings import PIVSettings
from plenopiv.reconstruction.choose import estimate_nnz
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.workflow import planning, rates
from small_case import volume_script

MM = 1e-3


def user_box(voxel=0.26e-3):
    """The box a new user typed for the small camera (issue #15)."""
    return VolumeGrid.from_bounds((-7 * MM, 7 * MM), (-4.5 * MM, 4.5 * MM), (-5 * MM, 5 * MM),
                                  voxel=voxel)


def test_resolution_cell_and_near_focus(small_camera):
    cam = planning.camera_resolution(small_camera)
    b = footprint(small_camera)
    assert cam.footprint == pytest.approx(b)
    # depth cell = b S_o / D with D = f/N: 2.24 mm for the 135 mm lens at f/2.8
    so = small_camera.object_distance
    d = small_camera.main_lens.focal_length / small_camera.main_lens.f_number
    assert cam.depth_cell == pytest.approx(b * so / d)
    assert cam.depth_cell == pytest.approx(2.237e-3, rel=1e-3)
    assert cam.near_focus == cam.depth_cell
    # a stopped-down recording has a longer depth cell
    assert planning.camera_resolution(small_camera, 5.6).depth_cell == pytest.approx(
        2 * cam.depth_cell)


@pytest.mark.parametrize("name", ["small_test", "small_m1"])
def test_weight_count_matches_the_light_field(name):
    """The pattern count is within 5 % of the sampled count of the real weights."""
    cam = load_camera(name)
    lf = light_field(Calibration.from_camera(cam))
    for grid in (user_box(), VolumeGrid.from_bounds((-2 * MM, 2 * MM), (-1 * MM, 3 * MM),
                                                    (-8 * MM, 2 * MM), voxel=0.2 * MM)):
        n_rays, nnz = planning.estimate_size(cam, grid)
        assert n_rays == pytest.approx(lf.n_rays, rel=0.05)
        assert nnz == pytest.approx(estimate_nnz(lf, grid, sample=13), rel=0.05)


def test_vectors_per_pass_as_the_piv_lays_them_out():
    from plenopiv.piv.windows import _window_layout

    assert planning.vectors_per_pass((18, 69, 108), [(8, 32, 32), (6, 24, 24)], 0.5, 3) == (
        (3, 3, 5), (5, 4, 8), (5, 4, 8))
    assert planning.vectors_per_pass((15, 40, 40), [(24, 16, 16)], 0.5, 1) == ((0, 4, 4),)
    for shape, w, ov in (((49, 35, 51), (12, 12, 12), 0.5), ((38, 35, 54), (16, 12, 12), 0.75),
                         ((20, 30, 40), (7, 9, 11), 0.3)):
        layout = _window_layout(shape, w, ov)
        assert planning.vectors_per_pass(shape, [w], ov, 1)[0] == tuple(
            len(s) for s in layout.starts)


def test_users_box_gets_concrete_advice(small_camera):
    p = planning.plan(small_camera, user_box())
    assert p.fits and not p.warnings
    text = " ".join(p.advice)
    assert "half a footprint" in text and "0.13 mm" in text
    assert "depth voxel" in text and "0.556 mm" in text
    # the tables to paste load as they are, and give the recommended grid
    toml = tomllib.loads(p.recommended_toml())
    grid = volume_from_dict(toml["volume"])
    assert grid.shape == p.recommended_grid.shape == (18, 69, 108)
    assert [tuple(w) for w in toml["piv"]["windows"]] == list(p.recommended_windows)
    assert p.recommended_windows == ((8, 32, 32), (6, 24, 24))
    assert min(p.recommended_vectors) >= planning.MIN_VECTORS_LAST_PASS


def test_windows_that_do_not_fit_are_a_warning(small_camera):
    grid = VolumeGrid.from_bounds((-3 * MM, 3 * MM), (-3 * MM, 3 * MM), (-2 * MM, 2 * MM),
                                  voxel=0.26 * MM)
    p = planning.plan(small_camera, grid)
    assert not p.fits
    w = " ".join(p.warnings)
    assert "do not fit" in w and "z: window 24 voxels > 15 voxels" in w
    assert "windows larger than the volume" in w
    # and the recommended windows for this box do fit
    assert all(min(v) > 0 for v in planning.vectors_per_pass(
        p.recommended_grid.shape, p.recommended_windows, 0.5, 3))


def test_box_outside_the_field_of_view(small_camera):
    grid = VolumeGrid.from_bounds((-10 * MM, 10 * MM), (-4 * MM, 4 * MM), (-5 * MM, 5 * MM),
                                  voxel=(0.13 * MM, 0.13 * MM, 0.556 * MM))
    p = planning.plan(small_camera, grid, piv=PIVSettings(windows=[(8, 32, 32), (6, 24, 24)]))
    assert any("field of view" in w for w in p.warnings)


def test_full_camera_uses_the_lattice_projector_and_its_memory(auburn_camera):
    grid = VolumeGrid.from_bounds((-37 * MM, 37 * MM), (-25 * MM, 25 * MM),
                                  (-26 * MM, 26 * MM), voxel=0.26 * MM)
    # footprint voxels without subdivision: docs/performance.md, 3.5 GB peak for the 16 MP
    # pair
    # (on the box's own 200 depth slices, as measured)
    p = planning.plan(auburn_camera, grid, memory_total=24e9,
                      reconstruction=ReconstructionSettings(lateral_subdivision=1,
                                                            depth_binning=1))
    assert p.projector == "lattice" and p.decision.subdivision == (1, 1)
    assert p.nnz > 1e10               # docs/performance.md: 1.23e10 non-zeros, ~100 GB of CSR
    assert p.n_rays == pytest.approx(11.55e6, rel=0.03)
    assert 2.5e9 < p.memory["peak"] < 5e9
    assert 20 < p.time["pair"] < 200
    assert p.time_model.startswith("benchmark rates")
    # the default: a 3 x 3 subdivision would hold 100 million working voxels, so "auto"
    # takes 2 x 2 (45 million) and says so: 67 s and 6.0 GB a volume measured
    auto = planning.plan(auburn_camera, grid, memory_total=24e9,
                         reconstruction=ReconstructionSettings(depth_binning=1))
    assert auto.decision.subdivision == (2, 2)
    assert p.memory["peak"] < auto.memory["peak"] < 8e9
    assert any("lateral_subdivision = 3" in w for w in auto.warnings)
    # and by default on working slices three deep (a third of the 2.24 mm depth cell): the
    # same lateral subdivision, a third of the slices, less time and memory
    binned = planning.plan(auburn_camera, grid, memory_total=24e9)
    assert binned.decision.subdivision == (2, 2) and binned.decision.depth_binning == 3
    assert binned.decision.working_shape[0] == -(-grid.shape[0] // 3)
    assert binned.time["volume"] < 0.5 * auto.time["volume"]
    assert binned.memory["peak"] < auto.memory["peak"]
    # a 3 x 3 subdivision asked for: 7.1 GB peak and 385 s for the pair on a shared 2-core
    # machine (docs/performance.md#full-camera-scale)
    p = planning.plan(auburn_camera, grid, memory_total=24e9,
                      reconstruction=ReconstructionSettings(lateral_subdivision=3,
                                                            depth_binning=1))
    assert p.projector == "lattice" and p.decision.subdivision == (3, 3)
    assert 6e9 < p.memory["peak"] < 15e9
    assert 200 < p.time["pair"] < 1000


def test_measured_rates_are_positive(small_camera):
    grid = VolumeGrid.from_bounds((-2 * MM, 2 * MM), (-2 * MM, 2 * MM), (-3 * MM, 3 * MM),
                                  voxel=(0.13 * MM, 0.13 * MM, 0.556 * MM))
    cfg = PIVSettings(windows=[(6, 16, 16)], passes=2)
    r = rates.measure_rates(small_camera, grid, piv=cfg, budget_s=0.5)
    assert r.source == "measured" and r.threads >= 1
    for v in (r.build_s_per_nnz, r.sweep_s_per_nnz, r.lattice_s_per_ray_slice,
              r.piv_s_per_window_voxel):
        assert math.isfinite(v) and 0 < v < 1e-3
    p = planning.plan(small_camera, grid, piv=cfg, rates=r)
    assert p.time_model.startswith("rates measured")
    assert p.time["pair"] == pytest.approx(p.time["weights"] + p.time["recording_check"]
                                           + p.time["first_volume"] + 2 * p.time["volume"]
                                           + p.time["piv"] + p.time["track"])


def test_cli_plan_experiment_human_and_json(tmp_path, capsys):
    exp = tmp_path / "exp.toml"
    exp.write_text('camera = "small_test"\n[volume]\nx_mm = [-7, 7]\ny_mm = [-4.5, 4.5]\n'
                   'z_mm = [-5, 5]\nvoxel_mm = 0.26\n')
    assert main(["plan", str(exp), "--no-measure"]) == 0
    out = capsys.readouterr().out
    for text in ("resolution cell", "near-focus zone", "recommended", "memory", "time model",
                 "voxel_mm = [0.13, 0.13, 0.556]"):
        assert text in out
    assert "np.float64" not in out and "e-1" not in out
    assert "the first 0 s more" not in out      # not rehearsed: the first volume's extra unknown
    assert main(["plan", str(exp), "--no-measure", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["command"] == "plan" and s["kind"] == "experiment"
    assert s["resolution_cell_mm"]["lateral"] == pytest.approx(0.2596, abs=1e-4)
    assert s["volume"]["shape"] == [38, 35, 54] and s["windows_fit"]
    assert s["recommended"]["voxel_mm"][2] == pytest.approx(0.5556, abs=1e-3)
    # the box options replace the experiment's; windows left unset are chosen to fit it
    assert main(["plan", str(exp), "--no-measure", "--json", "--z-mm", "-2", "2"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["windows_fit"]
    chosen = [f["kind"] for f in s["judgement"]["findings"] if f["severity"] == "chosen"]
    assert chosen == ["windows"]
    # windows given are kept, and judged
    assert main(["plan", str(exp), "--no-measure", "--json", "--z-mm", "-2", "2",
                 "--windows", "24", "16", "16"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["windows_vox"] == [[24, 16, 16]]
    assert not s["windows_fit"] and s["warnings"]


def test_cli_plan_camera_with_box(capsys):
    assert main(["plan", "small_m1", "--no-measure", "--json", "--x-mm", "-2", "2",
                 "--y-mm", "-2", "2", "--z-mm", "-3", "3"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["kind"] == "camera"
    assert s["volume"]["x_mm"] == pytest.approx([-2, 2])
    # a camera alone: the recommended voxel, and windows that fit
    assert np.allclose(s["volume"]["voxel_mm"], s["recommended"]["voxel_mm"], rtol=0.05)
    assert s["windows_fit"]


def test_cli_plan_needs_the_image_distance(tmp_path, capsys):
    from plenopiv.camera.model import PRESET_DIR

    raw = (PRESET_DIR / "small_test.toml").read_text()
    assert "image_distance_mm = 200.0\n" in raw
    cam = tmp_path / "cam.toml"
    cam.write_text(raw.replace("image_distance_mm = 200.0\n", ""))
    assert main(["plan", str(cam), "--no-measure"]) == 2
    assert "image_distance_mm" in capsys.readouterr().err
    assert main(["plan", str(cam), "--no-measure", "--image-distance-mm", "200", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["footprint_mm"] == pytest.approx(0.2596, abs=1e-4)


_PEAK_SCRIPT = volume_script(n_particles=270, seed=1) + """
import resource
try:    # this process's own peak (ru_maxrss keeps a parent's peak across fork and exec)
    status = open("/proc/self/status").read()
    print(int(status.split("VmHWM:")[1].split()[0]) * 1024)
except OSError:
    print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * (1 if sys.platform == "darwin"
                                                                  else 1024))
"""


def test_the_planned_peak_memory_is_the_measured_one_within_a_fifth():
    """A process that renders and reconstructs the demo's box (its simulator's light included)
    peaks within 20 % of what the plan says the reconstruction needs: the plan is neither a
    loose bound nor short (benchmarks/plan_accuracy.py measures it on more cases, with the
    time)."""
    import subprocess
    import sys

    from plenopiv.workflow.vortex_case import VortexCase, aligned_grid

    cam = load_camera("small_m1")
    p = planning.plan(cam, aligned_grid(cam, VortexCase()))
    predicted = max(p.memory["reconstruct_peak"], p.memory["weights_build_peak"])
    out = subprocess.run([sys.executable, "-c", _PEAK_SCRIPT], check=True, capture_output=True,
                         text=True).stdout
    measured = float(out.strip().splitlines()[-1])
    assert 0.8 <= predicted / measured <= 1.2, (predicted / 1e9, measured / 1e9)


def test_the_rehearsal_stands_only_for_the_reconstruction_it_rehearsed(small_camera):
    """Figures rehearsed with another projector, subdivision or sweep count are not used."""
    grid = user_box()
    base = planning.plan(small_camera, grid, rates=rates.BENCHMARK_RATES)
    choice = base.decision
    reh = rates.Rehearsal(weights_s_per_ray=1e-6, volume_s_per_ray_slice=1e-8,
                          first_s_per_ray_slice=2e-9, check_s_per_pixel=3e-7,
                          projector=choice.projector, subdivision=tuple(choice.subdivision),
                          iterations=10)
    rehearsed = planning.plan(small_camera, grid,
                              rates=dataclasses.replace(rates.BENCHMARK_RATES, rehearsal=reh))
    t = rehearsed.time
    assert t["weights"] == pytest.approx(1e-6 * choice.n_rays)
    # per working slice
    assert t["first_volume"] == pytest.approx(2e-9 * choice.n_rays * choice.grid.shape[0])
    assert t["pair"] == pytest.approx(t["weights"] + t["recording_check"] + t["first_volume"]
                                      + 2 * t["volume"] + t["piv"] + t["track"])
    assert "rehearsed" in rehearsed.time_model
    for other in (dict(projector="sparse"), dict(subdivision=(1, 1)), dict(iterations=5)):
        p = planning.plan(small_camera, grid, rates=dataclasses.replace(
            rates.BENCHMARK_RATES, rehearsal=dataclasses.replace(reh, **other)))
        assert p.time["first_volume"] == 0.0 and "rehearsed" not in p.time_model
        assert p.time["volume"] == pytest.approx(base.time["volume"])


def test_the_planned_time_is_the_measured_one_within_a_factor_of_two():
    """The demo's box planned with the reconstruction rehearsed, against one ``reconstruct``
    of it in this process. benchmarks/plan_accuracy.py holds the plan within 20 % on an idle
    machine, from the small cameras to the 16 MP one (docs/performance.md); on a shared
    machine a test holds a factor of two, which a model that leaves out a stage misses (the
    16 MP camera's weights were planned at a sixth of their time before the rehearsal)."""
    import time

    from plenopiv.synthetic.flows import Uniform
    from plenopiv.synthetic.seeding import SeedingBox, simulate_pair
    from plenopiv.workflow.volume import reconstruct_volume
    from plenopiv.workflow.vortex_case import VortexCase, aligned_grid

    cam = load_camera("small_m1")
    grid = aligned_grid(cam, VortexCase())
    measured_rates = rates.measure_rates(cam, grid, reconstruction=ReconstructionSettings(),
                                         budget_s=0.5)
    assert measured_rates.rehearsal is not None
    p = planning.plan(cam, grid, rates=measured_rates)
    assert "rehearsed" in p.time_model and p.time["first_volume"] >= 0
    b = grid.bounds
    pair = simulate_pair(cam, Uniform((0.0, 0.0, 0.0)), dt=1e-3,
                         box=SeedingBox(tuple(b[0]), tuple(b[1]), tuple(b[2])),
                         n_particles=270, rng=np.random.default_rng(1), rays_per_particle=256)
    image = np.asarray(pair.image_a, float)
    cal = Calibration.from_camera(cam)
    half = VolumeGrid.from_bounds(*(tuple(lo + (hi - lo) * f for f in (0.25, 0.75))
                                    for lo, hi in b), voxel=grid.voxel)
    reconstruct_volume(cal, image, half)              # the kernels compiled or loaded
    t0 = time.perf_counter()
    reconstruct_volume(cal, image, grid)
    measured = time.perf_counter() - t0
    assert 0.5 <= p.time["reconstruct"] / measured <= 2.0, (p.time, measured)


def test_a_turned_lattice_is_planned_with_measured_rates(small_camera):
    """A square lattice turned by 2 mrad and shifted (the per-lenslet projector): the rates
    are measured (the separable projector's on the lattice made straight) and the
    reconstruction rehearsed with the per-lenslet projector; ``plenopiv plan`` refused it."""
    mla = dataclasses.replace(small_camera.microlens_array, rotation=2e-3, offset=(3e-6, -2e-6))
    cam = small_camera.replace(microlens_array=mla)
    grid = VolumeGrid.from_bounds((-2 * MM, 2 * MM), (-2 * MM, 2 * MM), (-3 * MM, 3 * MM),
                                  voxel=0.26 * MM)
    settings = ReconstructionSettings(projector="lattice")    # matrix-free (small: explicit)
    r = rates.measure_rates(cam, grid, reconstruction=settings, budget_s=0.2)
    assert r.rehearsal is not None and r.rehearsal.projector == "lenslet"
    p = planning.plan(cam, grid, rates=r, reconstruction=settings)
    assert p.decision.projector == "lenslet" and "rehearsed" in p.time_model
    assert p.time["reconstruct"] > 0 and p.time["first_volume"] >= 0


@pytest.mark.parametrize("shift", [(0.0, 0.0), (0.37, 0.21), (-9.0, 4.6), (8.3, -9.8)])
def test_the_rehearsed_share_of_the_field_does_not_depend_on_where_the_box_lies(
        small_camera, shift):
    """A box moved within the field (by whole and by fractions of footprints) covers the same
    share of it, so the rehearsal runs the same patch; a box reaching past the field counts
    only what lies inside."""
    from plenopiv.synthetic.images import field_of_view

    b = footprint(small_camera)
    box = VolumeGrid.from_bounds((-3 * MM, 3 * MM), (-2 * MM, 2 * MM), (-3 * MM, 3 * MM),
                                 voxel=0.26 * MM)
    moved = VolumeGrid(tuple(np.array(box.origin) + np.array([*shift, 0.0]) * b), box.voxel,
                       box.shape)
    assert rates.covered_share(small_camera, moved) == pytest.approx(
        rates.covered_share(small_camera, box), abs=1e-12)
    half = field_of_view(small_camera)
    wide = VolumeGrid.from_bounds((-3 * half[0], 0.0), (-half[1], half[1]), (-MM, MM),
                                  voxel=0.26 * MM)
    assert rates.covered_share(small_camera, wide) == pytest.approx([0.5, 1.0], abs=0.02)


@pytest.mark.parametrize("correct, enabled", [(True, False), (False, True), (False, False)])
def test_the_pairs_tracks_count_in_the_pair_where_they_are_made(small_camera, correct,
                                                                 enabled):
    """[tracking] correct_vectors or enabled: the pair's time holds its tracks, at the
    stated seeding (or the top of the validated one, so that a pair seeded within it is not
    underestimated), in proportion to the particles; neither: none."""
    from plenopiv.tracking.settings import TrackingSettings
    from plenopiv.workflow.judgement import VALIDATED_SEEDING, lenslets_in_box

    grid = VolumeGrid(origin=(0.0, 0.0, 0.0), voxel=(1.25e-4, 1.25e-4, 2.5e-4),
                      shape=(16, 24, 32))
    tracking = TrackingSettings(correct_vectors=correct, enabled=enabled)
    plain = planning.plan(small_camera, grid, rates=rates.BENCHMARK_RATES,
                          tracking=TrackingSettings(correct_vectors=False))
    for seeding in (None, 0.1, 0.3):
        p = planning.plan(small_camera, grid, rates=rates.BENCHMARK_RATES, tracking=tracking,
                          seeding=seeding)
        if not (correct or enabled):
            assert p.time["track"] == 0.0 and p.time["pair"] == plain.time["pair"]
            continue
        per_lenslet = max(VALIDATED_SEEDING) if seeding is None else seeding
        expected = (planning.SECONDS_PER_TRACKED_PARTICLE * 2 * per_lenslet
                    * lenslets_in_box(p.camera, grid))
        assert p.time["track"] == pytest.approx(expected) and expected > 0
        assert p.time["pair"] == pytest.approx(plain.time["pair"] + expected)
