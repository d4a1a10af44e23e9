"""The judgement of an experiment's settings (plenopiv.workflow.judgement), and the commands
that say it: ``plan``, ``reconstruct``, ``piv`` and ``run`` warn with the same findings.

The worked example is the README's (docs/tutorial.md, configs/experiments/small_test.toml);
each variation changes one setting of it the way a user would.
"""

from __future__ import annotations

import dataclasses
import json
import tomllib

import h5py
import pytest

from conftest import REPO
from plenopiv.cli import main
from plenopiv.config.experiment import Experiment, experiment_from_dict
from plenopiv.piv.settings import PIVSettings
from plenopiv.workflow import planning
from plenopiv.workflow.judgement import (
    LOCKING_VOXEL_FOOTPRINTS,
    MIN_VECTORS_ALONG_AXIS,
    MIN_WINDOW_DEPTH_CELLS,
    PARTICLE_COUNT_RATIO,
    VALIDATED_SEEDING,
    camera_resolution,
    choose_unset,
    judge,
    judge_experiment,
    lenslets_in_box,
)

EXAMPLE = REPO / "configs" / "experiments" / "small_test.toml"


def example(**tables) -> dict:
    """The worked example's experiment table, with ``tables`` merged into its own."""
    cfg = tomllib.loads(EXAMPLE.read_text())
    for name, keys in tables.items():
        if keys is None:
            cfg.pop(name, None)
        else:
            cfg[name] = {**cfg.get(name, {}), **keys}
    return cfg


def judged(cfg: dict):
    exp = experiment_from_dict(cfg, base_dir=EXAMPLE.parent)
    cam = camera_resolution(exp.camera, exp.reconstruction.f_number)
    return exp, cam, *judge_experiment(exp, cam)


def kinds(findings, severity="warning") -> dict:
    return {f.kind: f for f in findings if f.severity == severity}


def test_the_worked_example_as_shipped_gives_no_finding():
    exp, _, out, j = judged(example())
    assert j.findings == () and out == exp


def test_windows_left_unset_are_chosen_as_the_example_gives_them():
    """The example's windows are what the planner recommends for its box: a file without them
    gets the same, said in a note, and no warning."""
    shipped, _, _, _ = judged(example())
    exp, _, out, j = judged(example(piv=None))
    assert exp.piv.windows != shipped.piv.windows                   # the class default
    assert out.piv.windows == shipped.piv.windows
    (note,) = j.findings
    assert note.severity == "chosen" and note.setting == "[piv] windows"
    assert "[[8, 32, 32], [6, 24, 24]]" in note.text


# the variations: (what a user changes, the kind warned, its figure, the limit it crossed)
VARIATIONS = {
    # the issue's case: a natural first voxel, the example's windows kept
    "voxel 0.25 mm": (dict(volume={"voxel_mm": 0.25}), "depth_window", 6 * 0.25 / 2.237,
                      MIN_WINDOW_DEPTH_CELLS),
    "no lateral subdivision": (dict(volume={"voxel_mm": [0.25, 0.25, 0.556]},
                                    reconstruction={"lateral_subdivision": 1}),
                               "lateral_voxel", 0.25 / 0.2596, LOCKING_VOXEL_FOOTPRINTS),
    "a thin box": (dict(volume={"y_mm": [-2.5, 2.5]}), "vectors", 2, MIN_VECTORS_ALONG_AXIS),
    "windows taller than the box": (dict(piv={"windows": [[24, 32, 32], [6, 24, 24]]}),
                                    "windows_fit", 1, None),
}


@pytest.mark.parametrize("name", VARIATIONS)
def test_each_variation_warns_with_its_figure_and_keeps_the_setting(name):
    tables, kind, figure, limit = VARIATIONS[name]
    exp, _, out, j = judged(example(**tables))
    found = kinds(j.findings)
    assert kind in found, [f.text for f in j.findings]
    f = found[kind]
    assert f.figure == pytest.approx(figure, rel=2e-3) and f.limit == limit
    assert f.change and f.setting
    assert out == exp                    # every setting given: nothing chosen, nothing changed
    assert not kinds(j.findings, "chosen")


def test_the_issues_voxel_gets_windows_that_measure_w():
    """voxel_mm = 0.25 with the example's windows: 0.67 depth cell deep windows and 2 vectors
    along y; the suggested windows clear both, and chosen when the windows are unset."""
    _, cam, _, j = judged(example(volume={"voxel_mm": 0.25}))
    assert set(kinds(j.findings)) == {"depth_window", "vectors"}
    assert "[[20, 16, 16], [16, 12, 12]]" in kinds(j.findings)["depth_window"].change
    exp, _, out, j = judged(example(volume={"voxel_mm": 0.25}, piv=None))
    assert out.piv.windows == ((20, 16, 16), (16, 12, 12))
    assert not kinds(j.findings)


def test_plan_finds_what_the_commands_find(small_camera):
    exp, cam, out, j = judged(example(volume={"voxel_mm": 0.25}))
    p = planning.plan(exp.camera, exp.volume, reconstruction=exp.reconstruction, piv=exp.piv)
    for f in j.warnings:
        assert f.text in p.warnings
        assert f.to_dict() in p.to_dict()["judgement"]["findings"]


@pytest.mark.parametrize(("ppl", "warned"), [(0.05, "below"), (0.1, "below"), (0.15, None),
                                             (0.3, None), (0.5, "above")])
def test_seeding_counted_from_a_particle_table(ppl, warned):
    """A table counts 0.76-1.08 of the particles seeded: the validated 0.15-0.3 per lenslet
    pass at either end, the example's 0.1 does not."""
    exp, cam, _, j = judged(example())
    lenslets = lenslets_in_box(cam, exp.volume)
    for ratio in ((1.0,) if warned else PARTICLE_COUNT_RATIO):
        _, f = j.with_seeding(ppl * ratio * lenslets)
        assert (f is None) == (warned is None), (ppl, ratio)
        if f is not None:
            assert warned in f.text and f.figure == pytest.approx(ppl)
    # a stated seeding (plan --seeding) is judged against the validated range itself
    stated = kinds(judge(cam, exp.volume, particles_per_lenslet=ppl))
    assert ("seeding" in stated) == (not VALIDATED_SEEDING[0] <= ppl <= VALIDATED_SEEDING[1])


def test_an_explicit_setting_is_never_changed():
    exp, cam, _, _ = judged(example(volume={"voxel_mm": 0.25}))
    odd = PIVSettings(windows=((4, 64, 64),), passes=1)
    for given in (frozenset({"piv.windows"}), None):         # in the file; built in Python
        piv, chosen = choose_unset(cam, exp.volume, odd, given)
        assert piv is odd and chosen == ()
    python = Experiment(camera=exp.camera, volume=exp.volume, piv=odd)
    assert judge_experiment(python, cam)[0] == python
    # unset with one pass: the last recommended window alone
    piv, (note,) = choose_unset(cam, exp.volume, dataclasses.replace(odd, passes=1),
                                frozenset())
    assert piv.windows == ((16, 12, 12),) and piv.passes == 1


# ---- the commands ----------------------------------------------------------------------------

#: One small experiment that is off in each way at once: footprint voxels reconstructed
#: without subdivision, windows 0.5 mm deep on a 0.55 mm depth cell, one vector along x and y,
#: and sparse seeding.
SMALL = ('camera = "small_m1"\n[volume]\nx_mm = [-1.0625, 1.0625]\ny_mm = [-1.0625, 1.0625]\n'
         'z_mm = [-1.5, 1.5]\nvoxel_mm = 0.125\n'
         '[reconstruction]\nlateral_subdivision = 1\niterations = 3\n'
         '[piv]\nwindows = [[4, 12, 12]]\npasses = 2\nuncertainty = "correlation"\n'
         '[images]\npairs = "pairs/*.h5"\ncalibration = "cal.h5"\ndt_s = 1e-3\n'
         '[output]\ndirectory = "out"\npng = false\nvtk = false\nweights_cache = ""\n')

SETTINGS_KINDS = {"lateral_voxel", "depth_window", "vectors"}


def _run(argv, capsys):
    code = main(argv)
    out, err = capsys.readouterr()
    assert code == 0, err
    return json.loads(out), err


def _settings_figures(judgement) -> dict:
    """The settings' findings, kind: figure (to 1e-9: a volume's grid is read back from its
    coordinates)."""
    return {f["kind"]: pytest.approx(f["figure"], rel=1e-9)
            for f in judgement["findings"] if f["kind"] in SETTINGS_KINDS}


def test_reconstruct_piv_run_and_plan_say_the_same_findings(tmp_path, capsys):
    from plenopiv.calibration.model import Calibration
    from plenopiv.camera.model import load_camera

    Calibration.from_camera(load_camera("small_m1")).save(tmp_path / "cal.h5")
    (tmp_path / "pairs").mkdir()
    pair = tmp_path / "pairs" / "p.h5"
    assert main(["simulate", "pair", "small_m1", "--n-particles", "30", "--rays-per-particle",
                 "256", "--depth-mm", "-1.5", "1.5", "--fill", "0.4", "--flow", "uniform",
                 "--no-tiff", "--quiet", "--out", str(pair)]) == 0
    exp = tmp_path / "exp.toml"
    exp.write_text(SMALL)
    capsys.readouterr()

    plan, _ = _run(["plan", str(exp), "--no-measure", "--json", "--seeding", "0.06"], capsys)
    figures = _settings_figures(plan["judgement"])
    assert set(figures) == SETTINGS_KINDS
    assert figures["depth_window"] == pytest.approx(0.5 / 0.55)
    assert figures["lateral_voxel"] == pytest.approx(1.0)
    assert "seeding" in {f["kind"] for f in plan["judgement"]["findings"]}

    vols = []
    for tag in ("a", "b"):
        vol = tmp_path / f"vol_{tag}.h5"
        s, err = _run(["reconstruct", str(tmp_path / "cal.h5"), f"{pair}:/image_{tag}",
                       "--config", str(exp), "--out", str(vol), "--json", "--quiet"], capsys)
        assert _settings_figures(s["judgement"]) == figures
        seeding = [f for f in s["judgement"]["findings"] if f["kind"] == "seeding"]
        assert seeding and seeding[0]["figure"] == s["judgement"]["particles_per_lenslet"]
        for f in s["judgement"]["findings"]:               # on stderr and in the JSON
            assert f"warning: {f['text']}" in err and f["text"] in s["warnings"]
        with h5py.File(vol) as fh:
            assert json.loads(fh.attrs["judgement"]) == s["judgement"]
        vols.append(vol)

    out = tmp_path / "vec.h5"
    s, err = _run(["piv", *map(str, vols), "--config", str(exp), "--out", str(out), "--json",
                   "--quiet", "--no-png", "--no-vtk"], capsys)
    assert _settings_figures(s["judgement"]) == figures
    assert "seeding" in {f["kind"] for f in s["judgement"]["findings"]}
    with h5py.File(out) as fh:                      # the windows given are the windows used
        assert list(fh.attrs["window_vox"]) == [4, 12, 12]
        assert json.loads(fh.attrs["judgement"]) == s["judgement"]

    s, err = _run(["run", str(exp), "--json", "--quiet", "--workers", "1"], capsys)
    assert _settings_figures(s["judgement"]) == figures
    assert s["n_done"] == 1
    (result,) = [r["result"] for r in s["results"]]
    assert any("particles per lenslet" in w for w in result["warnings"])
    with h5py.File(tmp_path / "out" / "p_vectors.h5") as fh:
        record = json.loads(fh.attrs["judgement"])
        assert list(fh.attrs["window_vox"]) == [4, 12, 12]
    assert _settings_figures(record) == figures
    assert "seeding" in {f["kind"] for f in record["findings"]}


@pytest.mark.parametrize(("voxel", "binning"), [(0.556, "auto"), (0.25, "auto"), (0.13, "auto"),
                                                (0.25, 1), (0.13, 2)])
def test_the_judgement_plan_and_reconstruction_record_the_same_depth_binning(voxel, binning):
    """What the products record, what plan reports and what the reconstruction builds: one
    depth binning, whatever the depth voxel typed."""
    from plenopiv.calibration.model import Calibration
    from plenopiv.reconstruction.choose import choose_reconstruction

    exp, _, _, j = judged(example(volume={"voxel_mm": [0.13, 0.13, voxel]},
                                  reconstruction={"depth_binning": binning}))
    built = choose_reconstruction(Calibration.from_camera(exp.camera), exp.volume,
                                  exp.reconstruction).depth_binning
    p = planning.plan(exp.camera, exp.volume, reconstruction=exp.reconstruction, piv=exp.piv)
    assert j.record()["depth_binning"] == built
    assert p.judgement().record()["depth_binning"] == built
    assert p.to_dict()["depth_binning"] == built
    if binning == "auto":       # a third of the 2.24 mm depth cell
        assert built == max(1, int(2.237 / 3 / voxel * 1.05))
