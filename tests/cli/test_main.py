"""The ``plenopiv`` command: products, --json summaries, and clear errors that write nothing."""

from __future__ import annotations

import json
import subprocess
import sys

import h5py
import numpy as np
import pytest
import tifffile

from plenopiv.cli import main


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_simulate_focal_point_writes_sensor_shaped_tiff(tmp_path, capsys, small_camera):
    out = tmp_path / "fp.tif"
    code, stdout, _ = run(capsys, "simulate", "focal-point", "small_test", "--out", str(out),
                          "--f-number", "16", "--json")
    assert code == 0
    summary = json.loads(stdout)
    assert summary["out"] == str(out) and summary["f_number"] == 16
    img = tifffile.imread(out)
    assert img.shape == small_camera.sensor.shape and img.dtype == np.uint16
    assert summary["shape"] == list(small_camera.sensor.shape)


@pytest.mark.parametrize("kind", ["alignment", "ruler", "particles"])
def test_simulate_other_images(tmp_path, capsys, kind):
    out = tmp_path / f"{kind}.tif"
    extra = ["--n-particles", "20", "--rays-per-particle", "256"] if kind == "particles" else []
    code, stdout, _ = run(capsys, "simulate", kind, "small_test", "--out", str(out), "--json",
                          *extra)
    assert code == 0, stdout
    assert json.loads(stdout)["command"] == f"simulate {kind}"
    assert tifffile.imread(out).max() > 0


def test_simulate_pair_writes_truth(tmp_path, capsys):
    out = tmp_path / "pair.h5"
    code, stdout, _ = run(capsys, "simulate", "pair", "small_test", "--out", str(out),
                          "--n-particles", "30", "--rays-per-particle", "256", "--json",
                          "--flow", "uniform", "--max-displacement-mm", "0.3", "--dt", "0.002")
    assert code == 0
    s = json.loads(stdout)
    with h5py.File(out) as fh:
        a, b = fh["/truth/position_a_m"][()], fh["/truth/position_b_m"][()]
        assert fh["/image_a"].shape == fh["/image_b"].shape == (700, 1040)
        assert fh["/truth/displacement_m"].attrs["units"] == "m"
        assert json.loads(fh.attrs["config"])["camera"]["sensor"]["rows"] == 700
        assert fh.attrs["dt_s"] == 0.002
    # uniform flow: every particle moves 0.3 mm along X
    assert np.allclose(b - a, [0.3e-3, 0, 0], atol=1e-12)
    assert s["max_displacement_mm"] == pytest.approx(0.3)
    assert all((tmp_path / f"pair_{t}.tif").exists() for t in "AB")


def test_bad_camera_is_a_clear_error_and_writes_nothing(tmp_path, capsys):
    cam = tmp_path / "cam.toml"
    cam.write_text("""
[sensor]
rows = 700
cols = 1040
pixel_pitch_um = 7.4
colour = true

[microlens_array]
rows = 41
cols = 61
pitch_um = -125.0
focal_length_um = 500.0
sensor_distance_um = 500.0

[main_lens]
focal_length_mm = 135.0
f_number = 16.0
image_distance_mm = 200.0
""")
    out = tmp_path / "x.tif"
    code, stdout, err = run(capsys, "simulate", "focal-point", str(cam), "--out", str(out),
                            "--json")
    assert code == 2
    assert "unknown key [sensor] colour" in err and "pitch_um" in err
    assert json.loads(stdout)["error_type"] == "ConfigError"
    assert list(tmp_path.iterdir()) == [cam]          # nothing written, no temporary left


def test_wrong_output_suffix_and_unknown_preset(tmp_path, capsys):
    code, _, err = run(capsys, "simulate", "alignment", "small_test", "--out",
                       str(tmp_path / "x.txt"))
    assert code == 2 and ".tif" in err
    code, _, err = run(capsys, "simulate", "alignment", "no_such_camera", "--out",
                       str(tmp_path / "x.tif"))
    assert code == 2 and "presets" in err and "small_test" in err
    assert not any(tmp_path.iterdir())


def test_console_script_runs():
    res = subprocess.run([sys.executable, "-m", "plenopiv.cli", "--version"],
                         capture_output=True, text=True, check=True)
    assert res.stdout.startswith("plenopiv ")


def test_sigterm_ends_a_verb_as_ctrl_c_does_with_its_own_status(monkeypatch, capsys):
    """A SIGTERM delivered while a verb runs: one line, exit 143, the handler put back."""
    import os
    import signal

    from plenopiv.cli import main, presets

    before = signal.getsignal(signal.SIGTERM)

    def slow(args):
        os.kill(os.getpid(), signal.SIGTERM)
        raise AssertionError("SIGTERM did not stop the verb")

    monkeypatch.setattr(presets, "cmd_presets", slow)
    assert main(["presets"]) == 143
    err = capsys.readouterr().err
    assert "terminated (SIGTERM)" in err and "Traceback" not in err
    assert signal.getsignal(signal.SIGTERM) is before


@pytest.mark.parametrize("after", ["works on", "returns"])
def test_a_sigterm_lost_in_a_finalizer_still_ends_the_verb_as_terminated(after, monkeypatch,
                                                                         capsys):
    """The first SIGTERM's Terminated raised inside a finalizer, where Python only prints it
    (numba's llvmlite frees objects in ``__del__`` while compiling; the verb then ran on and
    exited 0): the process sends itself SIGTERM again, and a verb that finishes before that
    ends as terminated all the same; nothing is printed but the one line; the handler and
    the unraisable hook are put back."""
    import os
    import signal
    import sys
    import time

    from plenopiv.cli import main, presets

    before, hook = signal.getsignal(signal.SIGTERM), sys.unraisablehook

    class Freed:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(100_000):             # the handler runs in here
                pass

    def losing(args):
        freed = Freed()
        del freed
        if after == "works on":
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline:
                time.sleep(0.01)
            raise AssertionError("the SIGTERM sent again did not stop the verb")
        return {"command": "presets"}

    monkeypatch.setattr(presets, "cmd_presets", losing)
    assert main(["presets"]) == 143
    err = capsys.readouterr().err
    assert err.strip().splitlines()[-1].startswith("error: terminated (SIGTERM)")
    assert "Traceback" not in err and "Exception ignored" not in err
    assert signal.getsignal(signal.SIGTERM) is before and sys.unraisablehook is hook


def test_after_a_sigterm_what_finalizers_raise_is_not_printed(monkeypatch, capsys):
    """The process the command owns drops finalizer failures once SIGTERM was taken (an
    llvmlite object half freed by the signal fails again later); before, they are shown."""
    import types

    from plenopiv import cli

    shown = []
    hook = cli.quiet_after_sigterm(lambda u: shown.append(u))
    monkeypatch.setattr(cli, "SIGTERM_RECEIVED", __import__("threading").Event())
    failure = types.SimpleNamespace(exc_value=AttributeError("_as_parameter_"))
    hook(failure)
    assert shown == [failure]
    cli.SIGTERM_RECEIVED.set()
    hook(failure)
    assert shown == [failure]
    assert capsys.readouterr().err == ""
