"""Clear messages: what the user wrote, the likely cause, memory named as memory.

Each test enumerates a class of message: every shape in which memory runs out reaches the
command as "out of memory" with the figures, never as a bug; every byte-order mark a TOML
file may carry is read or named; every refusal of a calibrated S_i names it as calibrated or
as the option that gave it; a particle image given as a calibration image is named as such,
whatever its density, and no grid type is blamed.
"""

from __future__ import annotations

import errno
import json
import resource

import pytest

from plenopiv.cli import main
from plenopiv.cli._memory import SIGNS

#: Every shape memory exhaustion takes on its way to the command, and the figure it carries
MEMORY_FAILURES = {
    "numpy": (MemoryError("Unable to allocate 574. MiB for an array with shape (700, 1040, "
                          "206) and data type float32"), "574. MiB"),
    "bare MemoryError": (MemoryError(), "no memory left"),
    "ENOMEM": (OSError(errno.ENOMEM, "Cannot allocate memory"), "Cannot allocate memory"),
    "shared library": (ImportError("/lib/_backend_agg.so: failed to map segment from shared "
                                   "object"), "failed to map segment"),
    "thread": (RuntimeError("can't start new thread"), "can't start new thread"),
    "C++": (RuntimeError("std::bad_alloc"), "std::bad_alloc"),
}


def _failing(exc):
    def command(args):
        raise exc
    return command


@pytest.mark.parametrize("shape", sorted(MEMORY_FAILURES))
@pytest.mark.parametrize("chained", [False, True], ids=["direct", "chained"])
def test_memory_running_out_is_named_with_its_figures(monkeypatch, capsys, shape, chained):
    from plenopiv.cli import presets

    exc, figure = MEMORY_FAILURES[shape]
    if chained:            # re-raised by a library as something else
        try:
            try:
                raise exc
            except Exception as inner:
                raise ValueError("while resampling the volume") from inner
        except ValueError as outer:
            exc = outer
    monkeypatch.setattr(presets, "cmd_presets", _failing(exc))
    limit = resource.getrlimit(resource.RLIMIT_AS)
    code = main(["presets", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 1 and out["error_type"] == "ResourceError"
    msg = out["error"]
    assert msg.startswith("out of memory (") and figure in msg and "a bug" not in msg
    assert "of memory is available" in msg and "ulimit -v" in msg
    if limit[0] != resource.RLIM_INFINITY:
        assert f"ulimit -v {limit[0] // 1024}" in msg


def test_every_sign_of_memory_is_recognised():
    from plenopiv.cli._memory import out_of_memory

    for sign in SIGNS:
        assert out_of_memory(RuntimeError(f"x: {sign.upper()} y")) is not None
    assert out_of_memory(RuntimeError("index 3 is out of bounds")) is None
    assert out_of_memory(OSError(errno.ENOENT, "No such file")) is None


def test_other_failures_stay_what_they_are(monkeypatch, capsys):
    from plenopiv.cli import presets

    monkeypatch.setattr(presets, "cmd_presets", _failing(OSError(errno.EIO, "I/O error")))
    assert main(["presets"]) == 1
    assert "a file operation failed" in capsys.readouterr().err
    monkeypatch.setattr(presets, "cmd_presets", _failing(IndexError("index 9")))
    assert main(["presets"]) == 1
    assert "a bug in plenopiv" in capsys.readouterr().err


@pytest.mark.parametrize("mark", ["", "\ufeff", "\ufeff\ufeff"], ids=["none", "BOM", "two"])
def test_a_utf8_byte_order_mark_is_no_key(tmp_path, capsys, mark):
    from plenopiv.camera.model import PRESET_DIR

    cam = tmp_path / "cam.toml"
    cam.write_bytes((mark + (PRESET_DIR / "small_m1.toml").read_text("utf-8")).encode())
    exp = tmp_path / "exp.toml"
    exp.write_bytes((mark + 'camera = "cam.toml"\n[volume]\nx_mm = [-1, 1]\ny_mm = [-1, 1]\n'
                     'z_mm = [-1, 1]\nvoxel_mm = 0.25\n').encode())
    assert main(["plan", str(exp), "--json"]) == 0, capsys.readouterr().err


@pytest.mark.parametrize("encoding", ["utf-16", "utf-32"])
def test_wide_text_and_a_joined_mark_are_named(tmp_path, capsys, encoding):
    from plenopiv.camera.model import PRESET_DIR

    text = (PRESET_DIR / "small_m1.toml").read_text("utf-8")
    cam = tmp_path / "cam.toml"
    cam.write_text(text, encoding=encoding)
    argv = ["simulate", "focal-point", str(cam), "--out", str(tmp_path / "fp.tif")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"is {encoding.upper()} text, not UTF-8" in err and "save it as UTF-8" in err
    cam.write_text(text + "\ufeff[main_lens]\n", encoding="utf-8")
    assert main(argv) == 2
    assert "holds a byte-order mark, U+FEFF" in capsys.readouterr().err


@pytest.mark.parametrize("option", ["plan", "simulate"])
def test_an_option_that_sets_s_i_is_named_as_the_option(tmp_path, capsys, option):
    """``--image-distance-mm 100`` on a 135 mm lens: the option is named, not the key."""
    if option == "plan":
        exp = tmp_path / "exp.toml"
        exp.write_text('camera = "small_test"\n[volume]\nx_mm = [-1, 1]\ny_mm = [-1, 1]\n'
                       'z_mm = [-1, 1]\nvoxel_mm = 0.25\n')
        argv = ["plan", str(exp), "--image-distance-mm", "100"]
    else:
        argv = ["simulate", "focal-point", "small_test", "--image-distance-mm", "100",
                "--out", str(tmp_path / "fp.tif")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--image-distance-mm 100: expected > [main_lens] focal_length_mm = 135" in err
    assert "image_distance_mm =" not in err


@pytest.fixture(scope="module")
def particle_images(tmp_path_factory):
    folder = tmp_path_factory.mktemp("particles")
    paths = {}
    for n in (5, 500, 10000):
        paths[n] = folder / f"p{n}.tif"
        assert main(["simulate", "particles", "small_test", "--n-particles", str(n), "--out",
                     str(paths[n]), "--quiet", "--seed", "4"]) == 0
    return paths


@pytest.mark.parametrize("n", [5, 500, 10000])
@pytest.mark.parametrize("role", ["--focal-point", "--alignment"])
def test_a_particle_image_as_a_calibration_image_is_named(particle_images, tmp_path, capsys,
                                                          n, role):
    """Few particles, many, or so many that the lit lenslets make a lattice with holes: the
    error says what the image shows and names the swap; it never blames the grid type."""
    from plenopiv.camera.model import load_camera
    from plenopiv.products.images import write_image
    from plenopiv.synthetic.images import focal_point_image

    capsys.readouterr()
    image = str(particle_images[n])
    argv = ["calibrate", "small_test", "--focal-point", image, "--out", str(tmp_path / "c.h5")]
    if role == "--alignment":
        fp = tmp_path / "fp.tif"
        write_image(fp, focal_point_image(load_camera("small_test"), f_number=16))
        argv = ["calibrate", "small_test", "--focal-point", str(fp), "--alignment", image,
                "--out", str(tmp_path / "c.h5")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    what = "the focal-point image" if role == "--focal-point" else "the alignment image"
    assert "particle image" in err and f"given as {what}?" in err, err
    assert "grid type" not in err
