"""The camera presets have one home, inside the package; what the docs and configs/ name exists."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

import plenopiv
from conftest import REPO
from plenopiv.camera.model import load_camera, preset_names, read_toml
from plenopiv.cli import main
from plenopiv.config.experiment import load_experiment


def test_presets_lists_every_preset_shipped_in_the_package(capsys):
    assert main(["presets", "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)["presets"]
    assert [p["name"] for p in listed] == preset_names() and len(listed) >= 4
    package = Path(plenopiv.__file__).parent
    for p in listed:
        assert Path(p["file"]).parent == package / "presets" and Path(p["file"]).is_file()
        cam = load_camera(p["name"])
        assert p["lenslets"] == [cam.microlens_array.rows, cam.microlens_array.cols]
        assert p["image_distance_mm"] == pytest.approx(cam.image_distance * 1e3)


def test_a_copied_preset_loads_as_the_same_camera(tmp_path, capsys):
    out = tmp_path / "my_camera.toml"
    assert main(["presets", "small_m1", "--out", str(out), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["out"] == str(out)
    assert load_camera(out).to_dict() == load_camera("small_m1").to_dict()


@pytest.mark.parametrize("argv, message", [
    (["presets", "no_such_camera"], "expected one of auburn_135mm"),
    (["presets", "--out", "x.toml"], "--out needs a preset NAME"),
    (["presets", "small_m1", "--out", "x.txt"], "expected a file ending in .toml"),
])
def test_presets_refuses_bad_input_with_exit_2(argv, message, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    assert message in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("argv", [
    ["plan", "configs/cameras/small_m1.toml", "--no-measure"],
    ["simulate", "alignment", "configs/cameras/small_m1.toml", "--out", "a.tif"],
])
def test_a_former_configs_cameras_path_names_the_preset(argv, tmp_path, monkeypatch, capsys):
    """A preset's file named by a path that does not exist here (configs/cameras/ typed
    outside the repository) is refused with an error that names the preset."""
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "the preset 'small_m1' ships inside plenopiv; name it 'small_m1'" in err


def test_configs_cameras_are_links_to_the_packaged_presets():
    """One home: every configs/cameras/*.toml is a link to the preset inside the package."""
    from plenopiv.camera.model import preset_names

    source = REPO / "src" / "plenopiv" / "presets"   # the package's presets in the checkout
    links = sorted((REPO / "configs" / "cameras").glob("*.toml"))
    assert sorted(p.stem for p in links) == sorted(preset_names())
    for p in links:
        assert p.is_symlink() and p.resolve() == (source / p.name).resolve()


def test_every_configs_path_in_the_docs_exists():
    pages = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
    text = "\n".join(p.read_text() for p in pages)
    paths = set(re.findall(r"configs/[a-z0-9_/.-]+\.toml", text))   # NAME: a placeholder
    assert paths, "README and docs/ name no configs/ file"
    missing = sorted(p for p in paths if not (REPO / p).is_file())
    assert not missing, f"README or docs/ name configs/ files the repository lacks: {missing}"


def test_every_preset_in_the_docs_table_is_shipped():
    text = (REPO / "docs" / "configuration.md").read_text()
    table = text[text.index("| preset | camera |"):].split("\n\n")[0]
    shown = re.findall(r"^\| `(\w+)` \|", table, re.M)
    assert sorted(shown) == preset_names()


@pytest.mark.parametrize("path", sorted((REPO / "configs" / "experiments").glob("*.toml")),
                         ids=lambda p: p.name)
def test_example_experiments_name_their_camera_by_preset(path):
    raw = read_toml(path, "experiment")["camera"]
    assert raw in preset_names()
    exp = load_experiment(path)
    assert exp.camera.to_dict() == load_camera(raw).to_dict()
