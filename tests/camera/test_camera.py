"""Camera model: loading, validation messages, lattice geometry and derived distances."""

from __future__ import annotations

import copy
import dataclasses
import math

import numpy as np
import pytest

from plenopiv.camera.model import (
    CameraModel,
    Substrate,
    camera_from_dict,
    camera_to_dict,
    load_camera,
    preset_names,
)
from plenopiv.camera.optics import propagation, system_matrix, thin_lens
from plenopiv.errors import ConfigError

BASE = {
    "name": "t",
    "sensor": {"rows": 700, "cols": 1040, "pixel_pitch_um": 7.4},
    "microlens_array": {"rows": 41, "cols": 61, "pitch_um": 125.0, "focal_length_um": 500.0,
                        "sensor_distance_um": 500.0},
    "main_lens": {"focal_length_mm": 135.0, "f_number": 16.0, "image_distance_mm": 200.0},
}


def with_change(path, value):
    cfg = copy.deepcopy(BASE)
    node = cfg
    for key in path[:-1]:
        node = node.setdefault(key, {})
    if value is None:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return cfg


def assert_close_tree(a, b):
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for k in a:
            assert_close_tree(a[k], b[k])
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            assert_close_tree(x, y)
    elif isinstance(a, float):
        assert math.isclose(a, b, rel_tol=1e-12, abs_tol=1e-15)
    else:
        assert a == b


def test_presets_load_and_round_trip():
    assert {"auburn_135mm", "auburn_50mm", "small_test"} <= set(preset_names())
    for name in preset_names():
        cam = load_camera(name)
        again = camera_from_dict(camera_to_dict(cam))
        assert_close_tree(camera_to_dict(again), camera_to_dict(cam))
    auburn = load_camera("auburn_135mm")
    assert auburn.sensor.shape == (3280, 4904)
    assert auburn.microlens_array.count == 193 * 287
    assert auburn.pitch_px == pytest.approx(125 / 7.4)


def test_units_are_converted_once_to_si():
    cam = camera_from_dict(BASE)
    assert cam.sensor.pixel_pitch == pytest.approx(7.4e-6)
    assert cam.microlens_array.pitch == pytest.approx(125e-6)
    assert cam.main_lens.focal_length == pytest.approx(0.135)
    assert cam.image_distance == pytest.approx(0.2)
    # S_o = f S_i / (S_i - f) = 135 · 200 / 65 mm, worked by hand: 415.385 mm, M = -0.48148
    assert cam.object_distance == pytest.approx(0.415385, rel=1e-5)
    assert cam.magnification == pytest.approx(-0.48148, rel=1e-4)
    # and the two planes are conjugate: the ray-transfer matrix object -> lens -> image has
    # B = 0 (every ray from an object point meets at one image point) and A = M
    m = system_matrix(propagation(cam.object_distance), thin_lens(0.135),
                      propagation(cam.image_distance))
    assert abs(m[0, 1]) < 1e-12
    assert m[0, 0] == pytest.approx(cam.magnification, rel=1e-9)


@pytest.mark.parametrize("path, value, expect", [
    (("sensor", "pixel_pitch_mm"), 7.4e-3, ["unknown key", "pixel_pitch_mm", "pixel_pitch_um"]),
    (("microlens_array", "pitch_um"), -125.0, ["pitch_um", "-125", "greater than 0"]),
    (("main_lens",), None, ["missing section", "main_lens"]),
    (("microlens_array", "pitch_um"), 14.0, ["pitch_um", "1.89", "at least 2 pixels"]),
    (("microlens_array", "cols"), 300, ["cols = 300", "wider than the sensor", "fit"]),
    (("microlens_array", "grid"), "triangle", ["grid", "triangle", "square", "hexagonal"]),
    (("microlens_array", "back_side"), "front", ["back_side", "physical", "thesis"]),
    (("main_lens", "image_distance_mm"), 100.0, ["image_distance_mm", "expected >", "135"]),
    (("main_lens", "f_number"), "fast", ["f_number", "fast"]),
])
def test_bad_config_names_key_value_and_expectation(path, value, expect):
    with pytest.raises(ConfigError) as info:
        camera_from_dict(with_change(path, value), source="cam.toml")
    msg = str(info.value)
    assert msg.startswith("cam.toml")
    for word in expect:
        assert word in msg, f"{word!r} missing from: {msg}"


def test_missing_file_and_bad_toml(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_camera(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[sensor\nrows = 3")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_camera(bad)


def test_square_lattice_is_centred_and_misplacement_follows_eq_3_13():
    cam = camera_from_dict(BASE)
    mla = cam.microlens_array
    c = mla.nominal_centres()
    assert c.shape == (41 * 61, 2)
    assert np.allclose(c.mean(axis=0), 0.0, atol=1e-15)
    # odd counts: the central lenslet sits on the axis
    assert np.allclose(c[(41 * 61) // 2], 0.0)
    gamma, so, to = 0.01, 20e-6, -13e-6
    moved = dataclasses.replace(mla, offset=(so, to), rotation=gamma).centres()
    s, t = c[:, 0], c[:, 1]
    expect_s = (s + so) * math.cos(gamma) - (t + to) * math.sin(gamma)
    expect_t = (s + so) * math.sin(gamma) + (t + to) * math.cos(gamma)
    assert np.allclose(moved[:, 0], expect_s) and np.allclose(moved[:, 1], expect_t)


def test_hexagonal_lattice_neighbours_are_one_pitch_apart():
    cam = camera_from_dict(with_change(("microlens_array", "grid"), "hexagonal"))
    c = cam.microlens_array.nominal_centres()
    p = cam.microlens_array.pitch
    assert np.allclose(c.mean(axis=0), 0.0, atol=1e-15)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(c).query(c, k=7)
    interior = np.all(np.abs(c) < np.array([0.3, 0.3]) * np.ptp(c, axis=0), axis=1)
    assert np.allclose(d[interior, 1:], p, rtol=1e-12)   # six neighbours at one pitch


def test_substrate_geometry_reproduces_thesis_section_5_1():
    # 50 mm lens at M = -1: S_i,eff = 100 mm; plate t = 6.3 mm, n = 1.46 -> l3 = 95.68 mm
    cfg = copy.deepcopy(BASE)
    cfg["main_lens"] = {"focal_length_mm": 50.0, "f_number": 16.0, "image_distance_mm": 100.0}
    cfg["microlens_array"]["substrate"] = {"thickness_mm": 6.3, "refractive_index": 1.46}
    cfg["external_interface"] = {"refractive_index": 1.33, "medium_depth_mm": 40.0}
    cam = camera_from_dict(cfg)
    assert cam.object_distance == pytest.approx(0.1)
    assert round(cam.l3 * 1e3, 2) == 95.68
    assert round(cam.interface_distance * 1e3, 2) == 69.92      # l2
    assert cam.mla_z == pytest.approx(cam.l3 + 6.3e-3)
    assert cam.focal_plane_z == pytest.approx(-(cam.interface_distance + 0.04))


def test_camera_model_is_frozen():
    cam = camera_from_dict(BASE)
    with pytest.raises(dataclasses.FrozenInstanceError):
        cam.name = "x"
    assert isinstance(cam.replace(name="y"), CameraModel)
    with pytest.raises(ConfigError, match="thickness"):
        Substrate(0.0, 1.5)


def test_patch_keeps_the_optics_and_cuts_the_sensor_to_the_micro_images():
    from plenopiv.camera.model import load_camera

    full = load_camera("auburn_50mm")
    p = full.patch(11, 21)
    assert (p.microlens_array.rows, p.microlens_array.cols) == (11, 21)
    assert p.main_lens == full.main_lens and p.sensor.pixel_pitch == full.sensor.pixel_pitch
    assert p.microlens_array.substrate == full.microlens_array.substrate
    # micro-image pitch on the sensor: p_m (1 + f/S_i) = 125 µm · 1.005 = 16.98 px of 7.4 µm
    spot_px = 125e-6 * (1 + 500e-6 / 100e-3) / 7.4e-6
    assert p.sensor.cols == math.ceil(21 * spot_px) + 6
    assert p.sensor.rows == math.ceil(11 * spot_px) + 6
    assert full.patch(11, 21, substrate=False).microlens_array.substrate is None
    with pytest.raises(ConfigError, match="patch"):
        full.patch(0, 3)
