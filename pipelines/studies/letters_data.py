"""The plenoptomos "letters" data set: where it lies, its optics file and its three images.

The data (``shared/data/plenoptomos_letters_ULF``, from cicwi/plenoptomos, GPL-3.0) are never
copied into this repository; :func:`find_data_dir` looks for them in the places
:func:`data_candidates` lists. :mod:`pipelines.studies.letters` analyses them.
"""

from __future__ import annotations

import configparser
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plenopiv.products.images import read_image

#: The repository root (this file is pipelines/studies/letters_data.py).
_REPO = Path(__file__).resolve().parents[2]

DATA_NAME = "plenoptomos_letters_ULF"
FILES = {"raw": "letters_ULF_M1.png", "white": "letters_ULF_M1_white.png",
         "dark": "letters_ULF_M1_dark.png", "ini": "letters_ULF_M1.ini"}


#: Where the data set comes from (for messages).
DATA_SOURCE = ("https://github.com/cicwi/plenoptomos, folder examples/data (letters_ULF_M1*.png "
               "and letters_ULF_M1.ini)")


def data_candidates() -> list[Path]:
    """Third-party data folders looked in, in order.

    ``$PLENOPIV_DATA``, ``../shared/data`` beside the current folder, and ``../shared/data``
    beside the repository that holds this study.
    """
    import os

    out = []
    if os.environ.get("PLENOPIV_DATA"):
        out.append(Path(os.environ["PLENOPIV_DATA"]))
    out.append(Path.cwd().parent / "shared" / "data")
    out.append(_REPO.parent / "shared" / "data")
    seen, unique = set(), []
    for p in out:
        key = str(p.resolve()) if p.exists() else str(p)
        if key not in seen:
            seen.add(key)
            unique.append(p)
    return unique


def _letters_in(folder: Path) -> Path:
    """``folder`` itself when it holds the images, else its ``plenoptomos_letters_ULF``."""
    return folder if (folder / FILES["raw"]).is_file() else folder / DATA_NAME


def find_data_dir(data: str | Path | None = None) -> Path:
    """The letters folder: under ``data``, else under the first candidate that holds it.

    ``data`` is the third-party data folder or the letters folder itself; the candidates are
    :func:`data_candidates`.

    Raises
    ------
    FileNotFoundError
        Naming the folders tried and where the data come from.
    """
    tried = [Path(data)] if data is not None else data_candidates()
    for folder in tried:
        d = _letters_in(folder)
        if all((d / f).is_file() for f in FILES.values()):
            return d
    names = ", ".join(str(_letters_in(f)) for f in tried)
    raise FileNotFoundError(f"the letters data set is not in {names}: get it from "
                            f"{DATA_SOURCE} into DIR/{DATA_NAME}/ and pass --data DIR (or set "
                            "PLENOPIV_DATA=DIR)")


def default_data_dir() -> Path:
    """The letters folder found by :func:`find_data_dir`, or where the repository expects it.

    Where it is expected: ``../shared/data/plenoptomos_letters_ULF`` beside the repository.
    """
    try:
        return find_data_dir()
    except FileNotFoundError:
        return _REPO.parent / "shared" / "data" / DATA_NAME


# --------------------------------------------------------------------------------------------
# Data and optics
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LettersData:
    """The three images (float64 counts, ``[row, col]``) and the optics from the .ini.

    Attributes
    ----------
    raw, white, dark : ndarray
        Raw lenslet image, white image, dark frame.
    optics : dict
        From :func:`read_optics`, SI units.
    """

    raw: np.ndarray
    white: np.ndarray
    dark: np.ndarray
    optics: dict


def read_optics(path: str | Path) -> dict:
    """Read the source's .ini (lengths in mm) into SI values.

    Returns
    -------
    dict
        ``pixel_pitch`` (m), ``sensor_declared`` (cols, rows) px, ``mla_pitch`` (m),
        ``lenslet_focal_length`` (m), ``mla_z`` and ``sensor_z`` (m, from the main lens),
        ``sensor_distance`` = sensor_z - mla_z (m), ``main_focal_length`` (m) and
        ``aperture_diameter`` (m).

    Notes
    -----
    ``[main_lens] aperture = 6.6`` is read as the stop diameter in mm (f/30.3). The source's
    own code reads its ``aperture`` keys as f-numbers, which is right for the lenslets
    (18.6 mm / 0.3 mm = f/62) but cannot be for the main lens: at f/6.6 the micro-images would
    be six pitches wide. :func:`calibrate_white` measures the micro-images to check.
    """
    cfg = configparser.ConfigParser()
    p = Path(path)
    if not cfg.read(p):
        raise FileNotFoundError(f"optics file {str(p)!r} not found or unreadable")
    mm = 1e-3
    try:
        mla_z = float(cfg["micro_lenses_array"]["z"]) * mm
        sensor_z = float(cfg["sensor"]["z"]) * mm
        return {
            "pixel_pitch": float(cfg["sensor"]["pixel_size_x"]) * mm,
            "sensor_declared": (int(cfg["sensor"]["size_x"]), int(cfg["sensor"]["size_y"])),
            "mla_pitch": float(cfg["micro_lens"]["physical_size_s"]) * mm,
            "lenslet_focal_length": float(cfg["micro_lens"]["f2"]) * mm,
            "mla_z": mla_z,
            "sensor_z": sensor_z,
            "sensor_distance": sensor_z - mla_z,
            "main_focal_length": float(cfg["main_lens"]["f1"]) * mm,
            "aperture_diameter": float(cfg["main_lens"]["aperture"]) * mm,
        }
    except (KeyError, ValueError) as exc:
        raise ValueError(f"optics file {str(p)!r}: missing or bad entry ({exc})") from None


def load_letters(data_dir: str | Path | None = None) -> LettersData:
    """Read the letters data set from ``data_dir`` (default :func:`default_data_dir`).

    Raises
    ------
    FileNotFoundError
        Naming the folder and the missing files.
    """
    d = Path(data_dir) if data_dir is not None else default_data_dir()
    missing = [f for f in FILES.values() if not (d / f).is_file()]
    if missing:
        raise FileNotFoundError(f"third-party data folder {str(d)!r} lacks {', '.join(missing)}; "
                                "the letters study needs the project's shared/data folder")
    imgs = {k: read_image(d / FILES[k]).astype(np.float64) for k in ("raw", "white", "dark")}
    shapes = {v.shape for v in imgs.values()}
    if len(shapes) != 1:
        raise ValueError(f"the raw, white and dark images differ in shape: {sorted(shapes)}")
    return LettersData(optics=read_optics(d / FILES["ini"]), **imgs)

