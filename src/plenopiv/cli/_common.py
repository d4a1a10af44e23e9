"""Shared by the commands: the argument parser class, common options, argument and output checks.

Each command checks its own arguments and output paths before any work; a bad value raises
:class:`~plenopiv.errors.ConfigError` (or :class:`~plenopiv.errors.OutputError`) naming the
flag, the value and what was expected.
"""

from __future__ import annotations

import argparse
import math
import re
from pathlib import Path
from typing import TYPE_CHECKING

from plenopiv.errors import ConfigError, PlenopivError
from plenopiv.products.files import check_output_path

if TYPE_CHECKING:
    from plenopiv.camera.model import CameraModel


class UsageError(PlenopivError):
    """A command line that argparse rejects (unknown option, missing or malformed value)."""


#: Negative numbers as option values: argparse's own pattern misses ``-1e-3`` and ``-inf``.
_NEGATIVE_NUMBER = re.compile(r"^-(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?$|^-(?:inf|infinity|nan)$",
                              re.IGNORECASE)


class _Parser(argparse.ArgumentParser):
    """argparse with plenopiv's error path; ``-1e-3`` is a value, not an option.

    A usage error raises :class:`UsageError` (one ``error:`` line, exit 2, JSON with
    ``--json``) instead of exiting.
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = _NEGATIVE_NUMBER

    def error(self, message):
        raise UsageError(f"{self.prog}: {message} (see {self.prog} --help)")


#: How the last line of every command's ``--help`` begins (:func:`_add_example`).
EXAMPLE_PREFIX = "example: "


class _HelpFormatter(argparse.HelpFormatter):
    """argparse's help, its example line (the epilog, :func:`_add_example`) as written.

    argparse would wrap a long example across lines; the description is wrapped as usual.
    """

    def _fill_text(self, text, width, indent):
        if text.startswith(EXAMPLE_PREFIX):
            return indent + text
        return super()._fill_text(text, width, indent)


def _add_example(p: argparse.ArgumentParser, example: str) -> None:
    """End ``p``'s ``--help`` with one line, ``example: EXAMPLE`` (a command to copy)."""
    p.epilog = EXAMPLE_PREFIX + example
    p.formatter_class = _HelpFormatter


def _add_common(p: argparse.ArgumentParser):
    p.add_argument("--json", action="store_true", help="print a one-object JSON summary")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _add_precompile(p: argparse.ArgumentParser, what: str):
    """``--no-precompile`` of the commands that render and calibrate before they reconstruct."""
    p.add_argument("--no-precompile", dest="precompile", action="store_false",
                   help="compile every numba kernel in this process (by default, on a first "
                   "run with two or more cores, the spot-detection, reconstruction and PIV "
                   f"kernels are compiled in two background processes while {what} renders "
                   "and calibrates)")


def _add_image_options(p: argparse.ArgumentParser):
    p.add_argument("--noise", choices=("none", "poisson"), default=None,
                   help="photon (Poisson) noise, default none (poisson with --realistic)")
    p.add_argument("--bit-depth", type=int, choices=(0, 8, 16), default=16,
                   help="integer quantisation; 0 writes float32 irradiance (default 16)")
    p.add_argument("--blur-px", type=float, default=0.0,
                   help="Gaussian blur sigma in pixels (default 0)")
    p.add_argument("--full-well", type=float, default=20000.0,
                   help="electrons at full scale, for photon noise (default 20000)")
    p.add_argument("--read-noise", type=float, default=None,
                   help="rms read noise, counts, with or without photon noise (default 0; 3 "
                        "with --realistic)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")


def _number(flag: str, value, *, minimum=None, maximum=None, open_min=False, open_max=False,
            unit: str = "") -> float | None:
    """A finite number within bounds; else a ConfigError naming the flag, value and range.

    None passes (an unset option).
    """
    if value is None:
        return None
    v = float(value)
    parts = []
    if minimum is not None:
        parts.append(f"{'>' if open_min else '>='} {minimum:g}")
    if maximum is not None:
        parts.append(f"{'<' if open_max else '<='} {maximum:g}")
    ok = math.isfinite(v)
    if ok and minimum is not None:
        ok = v > minimum if open_min else v >= minimum
    if ok and maximum is not None:
        ok = v < maximum if open_max else v <= maximum
    if not ok:
        rng = " and ".join(parts)
        raise ConfigError(f"{flag} {value!r}: expected a finite number"
                          + (f" {rng}" if rng else "") + (f" ({unit})" if unit else ""))
    return v


def _integer(flag: str, value, *, minimum: int, maximum: int) -> int | None:
    if value is None:
        return None
    if not minimum <= value <= maximum:
        raise ConfigError(f"{flag} {value}: expected an integer from {minimum} to {maximum}")
    return value


#: Largest seed accepted (numpy accepts any non-negative integer; the ray tracer takes 32 bits)
MAX_SEED = 2 ** 32 - 1


def _seed(value) -> int:
    return _integer("--seed", value, minimum=0, maximum=MAX_SEED)


def _input_files(*specs) -> list[str]:
    """The files among the command's inputs (file.h5:/dataset → file.h5; preset names out)."""
    from plenopiv.products.files import split_dataset_spec

    out = []
    for s in specs:
        if s is None:
            continue
        path, _ = split_dataset_spec(s)
        if path.exists():
            out.append(str(path))
    return out


def _check_out(path: str, suffixes: tuple[str, ...], inputs=(), beside=()) -> Path:
    """Check ``--out`` before any work: suffix, not a folder, writable, not an input.

    The files written beside it (``beside``: suffixes such as ".png") likewise.
    """
    p = check_output_path(path, suffixes=suffixes, inputs=inputs)
    for suffix in beside:
        check_output_path(p.with_suffix(suffix), inputs=inputs,
                          what=f"{suffix[1:].upper()} written beside --out")
    _remove_stale_temporaries([p, *(p.with_suffix(x) for x in beside)])
    return p


def _remove_stale_temporaries(paths) -> None:
    """Delete the hidden temporaries that a killed earlier run left for these outputs.

    They are ``.NAME.XXXXXXXX.part``, and ``.part.vti`` of the VTK writer.
    """
    import contextlib
    import glob

    for p in paths:
        if not p.parent.is_dir():
            continue
        for pattern in (f".{glob.escape(p.name)}.*.part", f".{glob.escape(p.name)}.*.part.*"):
            for t in p.parent.glob(pattern):
                with contextlib.suppress(OSError):
                    t.unlink()


def _camera_from_args(args) -> CameraModel:
    from plenopiv.camera.model import load_camera
    from plenopiv.resources import check_sensor

    cam = load_camera(args.camera)
    if getattr(args, "image_distance_mm", None) is not None:
        _number("--image-distance-mm", args.image_distance_mm, minimum=0, open_min=True)
        cam = cam.with_image_distance(args.image_distance_mm * 1e-3,
                                      origin="--image-distance-mm")
    if getattr(args, "lenslets", None) is not None:
        check_lenslets(args.lenslets, cam)
        cam = cam.patch(*args.lenslets)
    check_sensor(cam)
    return cam


def check_lenslets(lenslets, camera: CameraModel) -> None:
    """``--lenslets ROWS COLS``: a patch of the camera, so from 1 to its own lenslet counts.

    More lenslets than the camera has would render a sensor larger than the camera's.
    """
    rows, cols = camera.microlens_array.rows, camera.microlens_array.cols
    if not all(1 <= n <= most for n, most in zip(lenslets, (rows, cols), strict=True)):
        raise ConfigError(f"--lenslets {lenslets[0]} {lenslets[1]}: expected a patch of the "
                          f"camera, 1 to {rows} rows and 1 to {cols} columns of lenslets "
                          f"({camera.name!r}: {camera.sensor.rows} x {camera.sensor.cols} "
                          "pixels)")
