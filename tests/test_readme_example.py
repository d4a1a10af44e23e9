"""The README's worked example, run as written from the shipped example experiment files.

The commands are read from the first ``bash`` block under "## A worked example" in README.md
and run in a fresh folder, in order: ``cp`` lines copy (paths relative to the repository
root, as a user runs them from the clone), ``plenopiv`` lines run the command in-process
(the same ``main`` as the console script). Any other command fails the test, so the block
stays runnable. The vectors are then compared with the simulated flow: the planner's
settings must give a good field.
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from conftest import REPO
from plenopiv.cli import main
from plenopiv.config.experiment import load_experiment
from plenopiv.synthetic.flows import LambOseen

README = REPO / "README.md"


def readme_commands(heading: str = "## A worked example") -> list[list[str]]:
    """The commands of the first bash block after ``heading``: continuation lines joined,
    comments and blank lines dropped."""
    text = README.read_text()
    start = text.index(heading)
    block = re.search(r"```bash\n(.*?)```", text[start:], re.S).group(1)
    block = block.replace("\\\n", " ")
    out = []
    for line in block.splitlines():
        line = line.split(" #")[0].strip() if not line.lstrip().startswith("#") else ""
        if line:
            out.append(shlex.split(line))
    return out


def run_readme(commands, cwd: Path, capsys):
    summaries = []
    for argv in commands:
        if argv[0] == "cp":
            src = REPO / argv[1]
            assert src.exists(), f"README copies {argv[1]}, which the repository lacks"
            shutil.copy(src, cwd / argv[2])
            continue
        assert argv[0] == "plenopiv", f"README runs {argv[0]!r}: only cp and plenopiv here"
        code = main(argv[1:] + ["--json", "--quiet"])
        out, err = capsys.readouterr()
        assert code == 0, f"{' '.join(argv)} failed: {err}"
        summaries.append(json.loads(out))
    return summaries


def test_example_experiment_files_load_and_document_their_volume():
    for name in ("small_test", "auburn_135mm"):
        path = REPO / "configs" / "experiments" / f"{name}.toml"
        exp = load_experiment(path)
        assert exp.camera.name and exp.volume.n_voxels > 0
        text = path.read_text()
        assert "[lo, hi]" in text and "shape = [nz, ny, nx]" in text


@pytest.mark.slow
def test_readme_worked_example_runs_as_written(tmp_path, capsys, monkeypatch):
    commands = readme_commands()
    assert any(c[:2] == ["plenopiv", "plan"] for c in commands)
    monkeypatch.chdir(tmp_path)
    summaries = run_readme(commands, tmp_path, capsys)
    plan = next(s for s in summaries if s["command"] == "plan")
    assert plan["windows_fit"] and not plan["warnings"]
    assert (tmp_path / "vectors.h5").exists() and (tmp_path / "vectors.vti").exists()

    # the field against the simulated Lamb-Oseen vortex, at the window centres
    with h5py.File(tmp_path / "pair.h5") as fh:
        flow_cfg = json.loads(fh.attrs["config"])["flow"]
        dt = float(fh.attrs["dt_s"])
        n_true = len(fh["/truth/position_a_m"])
    flow = LambOseen(**{k: (tuple(v) if isinstance(v, list) else v)
                        for k, v in flow_cfg.items() if k != "kind"})
    with h5py.File(tmp_path / "vectors.h5") as fh:
        x, y, z = (fh[a][()] for a in "xyz")
        u, v, w = (fh[c][()] * dt for c in "uvw")          # m/s -> m
        valid = fh["/valid"][()].astype(bool)
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    from plenopiv.synthetic.flows import advect

    truth = (advect(flow, pts, dt / 2) - advect(flow, pts, -dt / 2)).T.reshape((3,) + X.shape)
    ok = valid
    corr = [np.corrcoef(m[ok], t[ok])[0, 1] for m, t in ((u, truth[0]), (w, truth[2]))]
    vol_a = next(s for s in summaries if s["command"] == "reconstruct")
    # the user's first guess (footprint voxels, default windows) found 88 of 250 particles
    # and correlated 0.49 (u) and 0.42 (w); the planner's settings: 191, 0.94 and 0.61
    assert vol_a["n_particles"] >= 0.6 * n_true
    assert valid.mean() >= 0.8
    print("README example:", vol_a["n_particles"], "of", n_true, "particles; valid",
          round(float(valid.mean()), 3), "corr u, w", np.round(corr, 3))
    assert corr[0] >= 0.85 and corr[1] >= 0.45, corr
