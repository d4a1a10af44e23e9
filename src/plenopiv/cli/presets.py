"""``plenopiv presets``: the camera presets shipped inside the package, listed or copied to edit.

A preset is used by its name wherever a camera is asked for (``plenopiv simulate pair
small_m1``, ``camera = "small_m1"`` in an experiment file); ``plenopiv presets NAME --out
FILE.toml`` writes a copy to edit into a camera file of one's own.
"""

from __future__ import annotations

from pathlib import Path

from plenopiv.cli._common import _add_common, _add_example, _check_out
from plenopiv.cli._output import _print_lines
from plenopiv.errors import ConfigError


def add_parser(sub) -> None:
    """Add ``presets`` to the subcommands ``sub``."""
    p = sub.add_parser("presets", help="the camera presets shipped with plenopiv (use them by "
                                       "name; copy one to edit with --out)")
    p.add_argument("name", nargs="?", help="the preset to show (default: list them all)")
    p.add_argument("--out", metavar="FILE.toml",
                   help="write a copy of preset NAME, a camera TOML file to edit")
    _add_common(p)
    _add_example(p, "plenopiv presets small_m1 --out my_camera.toml")
    p.set_defaults(func=cmd_presets)


def cmd_presets(args) -> dict:
    """List the presets, or show one and (with ``--out``) write a copy of its TOML file."""
    from plenopiv.camera.model import PRESET_DIR, preset_names
    from plenopiv.products.files import atomic_path

    names = preset_names()
    if args.name is None:
        if args.out is not None:
            raise ConfigError("--out needs a preset NAME: plenopiv presets NAME --out FILE.toml")
        return {"command": "presets", "presets": [describe_preset(n) for n in names]}
    if args.name not in names:
        raise ConfigError(f"preset {args.name!r}: expected one of {', '.join(names)}")
    summary = {"command": "presets", **describe_preset(args.name)}
    if args.out is not None:
        out = _check_out(args.out, (".toml",))
        text = (PRESET_DIR / f"{args.name}.toml").read_text(encoding="utf-8")
        with atomic_path(out) as tmp:
            tmp.write_text(text, encoding="utf-8")
        summary["out"] = str(out)
    return summary


def describe_preset(name: str) -> dict:
    """Name, description, file and main figures of the preset ``name`` (lengths in mm)."""
    from plenopiv.camera.model import PRESET_DIR, load_camera

    cam = load_camera(name)
    mla, lens = cam.microlens_array, cam.main_lens
    return {"name": name, "camera": cam.name, "file": str(PRESET_DIR / f"{name}.toml"),
            "sensor_px": list(cam.sensor.shape), "lenslets": [mla.rows, mla.cols],
            "focal_length_mm": lens.focal_length * 1e3, "f_number": lens.f_number,
            "image_distance_mm": cam.image_distance * 1e3}


def print_summary(summary: dict) -> None:
    """``plenopiv presets`` for people: one line per preset, or the one preset's figures."""
    if "presets" not in summary:
        _print_lines(summary)
        return
    rows = summary["presets"]
    width = max((len(r["name"]) for r in rows), default=0)
    for r in rows:
        print(f"{r['name'].ljust(width)}  {r['camera']}")
    if rows:
        print(f"files in {Path(rows[0]['file']).parent}; use a preset by its name, or write a "
              "copy to edit with: plenopiv presets NAME --out FILE.toml")
