"""Every TOML key is typed strictly: a boolean is no number, a number no text, a text no number.

The class is enumerated: every scalar key of the camera file and of every table of the
experiment file gets a value of each wrong kind, and each is refused naming the key.
"""

import copy
import dataclasses
import typing

import pytest

from plenopiv.camera.grid import volume_from_dict
from plenopiv.camera.model import _CameraCfg, camera_from_dict, camera_to_dict, load_camera
from plenopiv.config.experiment import ExperimentFile, experiment_from_dict
from plenopiv.errors import ConfigError
from plenopiv.settings import fields_of

VOLUME = {"x_mm": [-1.0, 1.0], "y_mm": [-1.0, 1.0], "z_mm": [-1.0, 1.0], "voxel_mm": 0.25}


def kinds(annotation) -> set[str]:
    """What a key takes: "number", "integer", "bool", "text" (scalars only)."""
    out = set()
    for a in typing.get_args(annotation) or (annotation,):
        if typing.get_origin(a) is typing.Literal:
            out |= {"text" if isinstance(v, str) else "integer" for v in typing.get_args(a)}
        elif a is bool:
            out.add("bool")
        elif a is int:
            out.add("integer")
        elif a is float:
            out.add("number")
        elif a is str:
            out.add("text")
        elif typing.get_args(a):
            out |= kinds(a)
    return out


def scalar_keys(model, prefix=()):
    """``(path, kinds)`` of every scalar key of a model, tables walked."""
    for name, info in fields_of(model).items():
        sub = info.annotation
        inner = [a for a in (typing.get_args(sub) or (sub,)) if a is not type(None)]
        table = next((a for a in inner if fields_of(a) is not None), None)
        if table is not None:
            yield from scalar_keys(table, prefix + (name,))
        elif typing.get_origin(sub) is not list:
            k = kinds(sub)
            if k:
                yield prefix + (name,), k


WRONG = {"bool": True, "text": "1", "number": 1.5, "integer": 2}


def wrong_values(accepted: set[str]):
    """A value of each kind the key does not take (an integer is a number too)."""
    takes = set(accepted) | ({"integer"} if "number" in accepted else set())
    return [(kind, v) for kind, v in WRONG.items() if kind not in takes]


def camera_cases():
    base = camera_to_dict(load_camera("small_test"))
    base["microlens_array"]["substrate"] = {"thickness_mm": 1.0, "refractive_index": 1.5}
    base["external_interface"] = {"refractive_index": 1.33}
    for path, accepted in scalar_keys(_CameraCfg):
        for kind, value in wrong_values(accepted):
            yield pytest.param(base, path, value, id=f"camera:{'.'.join(path)}={kind}")


def experiment_cases():
    base = {"camera": "small_test", "volume": dict(VOLUME)}
    for path, accepted in scalar_keys(ExperimentFile):
        if path in (("camera",),):
            continue
        for kind, value in wrong_values(accepted):
            yield pytest.param(base, path, value, id=f"experiment:{'.'.join(path)}={kind}")


def with_value(base, path, value):
    cfg = copy.deepcopy(base)
    d = cfg
    for part in path[:-1]:
        d = d.setdefault(part, {})
    d[path[-1]] = value
    return cfg


@pytest.mark.parametrize(("base", "path", "value"), list(camera_cases()))
def test_a_camera_key_of_the_wrong_type_is_refused_by_name(base, path, value):
    with pytest.raises(ConfigError, match=path[-1]):
        camera_from_dict(with_value(base, path, value))


@pytest.mark.parametrize(("base", "path", "value"), list(experiment_cases()))
def test_an_experiment_key_of_the_wrong_type_is_refused_by_name(base, path, value):
    with pytest.raises(ConfigError, match=path[-1]):
        experiment_from_dict(with_value(base, path, value))


@pytest.mark.parametrize("key", ["x_mm", "voxel_mm"])
@pytest.mark.parametrize("value", [True, "1"])
def test_a_volume_key_of_the_wrong_type_is_refused_by_name(key, value):
    cfg = dict(VOLUME)
    cfg[key] = value if key == "voxel_mm" else [value, 1.0]
    with pytest.raises(ConfigError, match=key):
        volume_from_dict(cfg)


def test_the_enumeration_reaches_every_table():
    tables = {path[0] for path, _ in scalar_keys(ExperimentFile) if len(path) > 1}
    assert {"reconstruction", "particles", "piv", "images", "batch", "output",
            "tracking"} <= tables
    assert len(list(experiment_cases())) > 60


def test_arrays_stand_for_tuples_and_integers_for_numbers():
    exp = experiment_from_dict({"camera": "small_test", "volume": dict(VOLUME),
                                "particles": {"box_vox": [2, 1, 1]},
                                "reconstruction": {"relaxation": 1}})
    assert exp.particles.box_vox == (2, 1, 1)
    assert exp.reconstruction.relaxation == 1.0
    assert dataclasses.is_dataclass(exp.particles)


def test_a_byte_order_mark_is_read_as_nothing(tmp_path):
    from plenopiv.config.experiment import load_experiment

    p = tmp_path / "exp.toml"
    p.write_bytes("\ufeffcamera = \"small_test\"\n[volume]\nx_mm = [-1, 1]\ny_mm = [-1, 1]\n"
                  "z_mm = [-1, 1]\nvoxel_mm = 0.25\n".encode())
    assert load_experiment(p).volume.shape == (8, 8, 8)
