"""The jobs of :mod:`plenopiv.batch`: pairs of images found on disk, and complete products.

A :class:`PairJob` names a pair, its two images and its product; :func:`discover_pairs`
finds them from glob patterns. A product is complete when its root attribute
:data:`COMPLETE_ATTR` is set (the last thing written) and, when the job carries one, it
records the job's identity (:data:`IDENTITY_ATTR`), so that a resumed batch skips exactly the
pairs already made with the same settings and inputs, whose other files (``companions``)
are all there, and that this plenopiv can read (:func:`_stale_reason`).
"""

from __future__ import annotations

import contextlib
import glob
import json
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from plenopiv.errors import ConfigError
from plenopiv.products.jsonio import dumps

#: Root attribute of a product that marks it complete (the last thing ``process`` writes).
COMPLETE_ATTR = "complete"
#: Root attribute of a product holding the identity (JSON) of the settings and inputs it was
#: made from.
IDENTITY_ATTR = "identity"

_H5_SUFFIXES = (".h5", ".hdf5")
_SEPARATORS = "_-. "


@dataclass(frozen=True)
class PairJob:
    """One image pair and the product it becomes.

    Parameters
    ----------
    name : str
        Unique name of the pair in its batch (the progress, the summary and the dask key use
        it); no path separators.
    image_a, image_b : str
        The first and second exposure: an image file (TIFF, PNG) or ``file.h5:/dataset``.
    output : Path
        The product of this pair, an HDF5 file (``.h5``/``.hdf5``).
    identity : mapping of str to str, optional
        What makes this pair's product (e.g. hashes of the settings, the calibration and the
        two images); stored in the product by ``process``, compared on resume.
    companions : tuple of Path
        The pair's other files (its volumes, side products), written before ``output``; a
        resumed batch recomputes the pair when one of them is missing.
    """

    name: str
    image_a: str
    image_b: str
    output: Path
    identity: Mapping[str, str] | None = field(default=None, compare=False)
    companions: tuple[Path, ...] = field(default=(), compare=False)

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name.strip() or "/" in self.name \
                or os.sep in self.name:
            raise ConfigError(f"pair name {self.name!r}: expected a non-empty string without "
                              "path separators")
        object.__setattr__(self, "image_a", str(self.image_a))
        object.__setattr__(self, "image_b", str(self.image_b))
        out = Path(self.output)
        if out.suffix.lower() not in _H5_SUFFIXES:
            raise ConfigError(f"pair {self.name!r}: output {str(out)!r} must be an HDF5 file "
                              "ending in .h5 or .hdf5 (its completeness is an HDF5 attribute)")
        object.__setattr__(self, "output", out)
        object.__setattr__(self, "companions", tuple(Path(p) for p in self.companions))

    def to_dict(self) -> dict:
        """Return the job as JSON-friendly values."""
        return {"name": self.name, "image_a": self.image_a, "image_b": self.image_b,
                "output": str(self.output),
                "identity": None if self.identity is None else dict(self.identity),
                "companions": [str(p) for p in self.companions]}


def _natural_key(s: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s)]


def _glob_regex(pattern: str) -> re.Pattern:
    """Build a regex matching what ``glob`` matches for ``pattern``, capturing wildcards."""
    out, i, n = [], 0, len(pattern)
    while i < n:
        c = pattern[i]
        if pattern.startswith("**/", i):
            out.append("((?:.*/)?)")
            i += 3
        elif pattern.startswith("**", i):
            out.append("(.*)")
            i += 2
        elif c == "*":
            out.append("([^/]*)")
            i += 1
        elif c == "?":
            out.append("([^/])")
            i += 1
        elif c == "[":
            j = i + 1
            if j < n and pattern[j] == "!":
                j += 1
            if j < n and pattern[j] == "]":
                j += 1
            j = pattern.find("]", j)
            if j < 0:
                out.append(re.escape(c))
                i += 1
                continue
            body = pattern[i + 1:j]
            if body.startswith("!"):
                body = "^" + body[1:]
            out.append("([" + body.replace("\\", "\\\\") + "])")
            i = j + 1
        else:
            out.append(re.escape(c))
            i += 1
    return re.compile("".join(out) + r"\Z")


def _matches(pattern: str, root: Path, what: str) -> list[tuple[str, Path]]:
    """Return ``[(key, absolute path)]`` of the files matching ``pattern``, sorted."""
    pattern = str(pattern)
    found = [p for p in glob.glob(pattern, root_dir=root, recursive=True)
             if (root / p).is_file()]
    if not found:
        raise ConfigError(f"{what} {pattern!r} matches no file (looked in {str(root)!r})")
    rx = _glob_regex(pattern)
    out = []
    for p in found:
        m = rx.match(p)
        key = "\x00".join(m.groups()) if m else Path(p).stem
        out.append((key, (root / p).resolve()))
    out.sort(key=lambda kp: _natural_key(str(kp[1])))
    return out


def _pair_name(a: Path, b: Path) -> str:
    prefix = os.path.commonprefix([a.stem, b.stem]).rstrip(_SEPARATORS)
    return prefix


def discover_pairs(pattern_a: str, pattern_b: str | None = None, *, out_dir: str | Path,
                   pair_by: str = "auto", root: str | Path | None = None,
                   output_name: str = "{name}.h5",
                   datasets: tuple[str, str] = ("/image_a", "/image_b")) -> list[PairJob]:
    """Build the jobs of a batch from glob patterns.

    Two patterns (``images/*_A.tif``, ``images/*_B.tif``) pair the files of the first with
    those of the second; one pattern of HDF5 files (``pairs/*.h5``) makes one job per file,
    its exposures read from the datasets ``datasets`` (``/image_a`` and ``/image_b``).

    Parameters
    ----------
    pattern_a, pattern_b : str
        Glob patterns (``**`` recurses), relative to ``root``. Hidden files are not matched.
    out_dir : str or Path
        Folder of the products, relative to ``root``.
    pair_by : {"auto", "stem", "order"}
        ``"stem"``: files pair when the parts matched by the wildcards agree
        (``run_07_A.tif`` with ``run_07_B.tif``); a file without partner is an error.
        ``"order"``: the i-th file of each pattern in natural sort order (``frame_2`` before
        ``frame_10``). ``"auto"`` (default): by stem when the two patterns' wildcard parts
        agree, in order when they share none at all (``A_0001.tif`` / ``B_0001.tif`` under
        ``A/*.tif`` / ``B/*.tif``), and an error when they agree only in part (files missing).
    root : str or Path, optional
        Folder the patterns and ``out_dir`` are relative to (default: the current folder);
        e.g. the experiment file's folder.
    output_name : str
        File name of each product; ``{name}`` is the pair's name (the common start of the two
        file stems, ``run_07`` above; the first file's stem when that is empty or not unique).
    datasets : (str, str)
        The exposures' datasets in one-file-per-pair mode.

    Returns
    -------
    list of PairJob
        In natural sort order of the first exposure, with absolute paths.

    Raises
    ------
    ConfigError
        When a pattern matches nothing, the counts differ, a file has no partner, two pairs get
        the same name, or a product would overwrite an input.
    """
    if pair_by not in ("auto", "stem", "order"):
        raise ConfigError(f"pair_by {pair_by!r}: expected one of 'auto', 'stem', 'order'")
    if "{name}" not in output_name or not output_name.lower().endswith(_H5_SUFFIXES):
        raise ConfigError(f"output_name {output_name!r}: expected a file name containing "
                          "'{name}' and ending in .h5")
    base = Path.cwd() if root is None else Path(root)
    if not base.is_dir():
        raise ConfigError(f"root {str(base)!r} is not a folder")
    out = (base / out_dir).resolve()
    a = _matches(pattern_a, base, "pattern_a")
    if pattern_b is None:
        not_h5 = [str(p) for _, p in a if p.suffix.lower() not in _H5_SUFFIXES]
        if not_h5:
            raise ConfigError(f"pattern_a {pattern_a!r} without pattern_b expects one HDF5 file "
                              f"per pair holding {datasets[0]} and {datasets[1]}, but it "
                              f"matches {len(not_h5)} other files (first: {not_h5[0]!r}); "
                              "give the second exposures' pattern as pattern_b")
        triples = [(p.stem, f"{p}:{datasets[0]}", f"{p}:{datasets[1]}") for _, p in a]
        inputs = {p for _, p in a}
    else:
        b = _matches(pattern_b, base, "pattern_b")
        both = {p for _, p in a} & {p for _, p in b}
        if both:
            raise ConfigError(f"pattern_a {pattern_a!r} and pattern_b {pattern_b!r} both match "
                              f"{len(both)} files (first: {str(sorted(both)[0])!r}): each "
                              "exposure must match only one pattern")
        pairs = _pair_files(a, b, pattern_a, pattern_b, pair_by)
        names = [_pair_name(pa, pb) for pa, pb in pairs]
        if any(not n for n in names) or len(set(names)) != len(names):
            names = [pa.stem for pa, _ in pairs]
        triples = [(n, str(pa), str(pb)) for n, (pa, pb) in zip(names, pairs, strict=True)]
        inputs = {p for _, p in a} | {p for _, p in b}
    seen: dict[str, str] = {}
    for name, ia, _ in triples:
        if name in seen:
            raise ConfigError(f"two pairs get the name {name!r} ({seen[name]!r} and {ia!r}); "
                              "rename the files or use patterns that tell them apart")
        seen[name] = ia
    jobs = [PairJob(n, ia, ib, out / output_name.format(name=n)) for n, ia, ib in triples]
    clash = [j for j in jobs if j.output.resolve() in inputs]
    if clash:
        raise ConfigError(f"the product {str(clash[0].output)!r} of pair {clash[0].name!r} "
                          "would overwrite an input image; choose another out_dir or "
                          "output_name")
    return jobs


def _pair_files(a, b, pattern_a, pattern_b, pair_by) -> list[tuple[Path, Path]]:
    keys_a = {k: p for k, p in a}
    keys_b = {k: p for k, p in b}
    unique = len(keys_a) == len(a) and len(keys_b) == len(b)
    common = keys_a.keys() & keys_b.keys()
    if pair_by == "auto":
        if unique and common and len(common) == len(a) == len(b):
            pair_by = "stem"
        elif not common:
            pair_by = "order"
        else:
            pair_by = "stem"  # partial agreement: report the files without partner
    if pair_by == "order":
        if len(a) != len(b):
            raise ConfigError(f"pattern_a {pattern_a!r} matches {len(a)} files but pattern_b "
                              f"{pattern_b!r} matches {len(b)}: expected as many second as "
                              "first exposures")
        return [(pa, pb) for (_, pa), (_, pb) in zip(a, b, strict=True)]
    if not unique:
        raise ConfigError(f"pair_by='stem': the wildcards of {pattern_a!r} / {pattern_b!r} do "
                          "not tell the files apart; use pair_by='order' ([images] pair_by = "
                          "\"order\" in an experiment file)")
    only_a = [str(keys_a[k]) for k in keys_a.keys() - common]
    only_b = [str(keys_b[k]) for k in keys_b.keys() - common]
    if only_a or only_b:
        parts = []
        if only_a:
            parts.append(f"{len(only_a)} first exposures have no second "
                         f"(e.g. {sorted(only_a)[:3]})")
        if only_b:
            parts.append(f"{len(only_b)} second exposures have no first "
                         f"(e.g. {sorted(only_b)[:3]})")
        raise ConfigError(f"pattern_a {pattern_a!r} ({len(a)} files) and pattern_b "
                          f"{pattern_b!r} ({len(b)} files) do not pair by their wildcard "
                          f"parts: {'; '.join(parts)}. Add the missing files, or use "
                          "pair_by='order' ([images] pair_by = \"order\" in an experiment "
                          "file) to pair them in sorted order")
    return [(p, keys_b[k]) for k, p in a]


# ---- completeness --------------------------------------------------------------------------


def mark_complete(path: str | Path, identity: Mapping[str, str] | None = None) -> None:
    """Mark the HDF5 product ``path`` complete: the root attribute ``complete = True``.

    Also ``identity``, the job's, when given.

    Call it as the last write of a product, after the file has been written and closed (or on
    the temporary path inside an :func:`plenopiv.products.files.atomic_path` block). See the module
    docstring for the contract.
    """
    import h5py

    with h5py.File(path, "r+") as fh:
        if identity is not None:
            fh.attrs[IDENTITY_ATTR] = dumps(dict(identity), sort_keys=True)
        fh.flush()
        fh.attrs[COMPLETE_ATTR] = True


def _stored(path: str | Path) -> tuple[dict | None, tuple]:
    """``(identity, (kind, schema_version, plenopiv_version))`` stored in a product.

    None where absent (or the file unreadable).
    """
    import h5py

    try:
        with h5py.File(path, "r") as fh:
            raw = fh.attrs.get(IDENTITY_ATTR)
            versions = (str(fh.attrs.get("product", "product")), fh.attrs.get("schema_version"),
                        fh.attrs.get("plenopiv_version"))
    except Exception:  # noqa: BLE001 - unreadable: no identity
        return None, ("product", None, None)
    out = None
    if raw is not None:
        try:
            out = json.loads(raw)
        except (TypeError, ValueError):
            out = None
    return (out if isinstance(out, dict) else None), versions


def product_identity(path: str | Path) -> dict | None:
    """The identity stored in a product (None when it has none or cannot be read)."""
    return _stored(path)[0]


_IDENTITY_WORDS = {"settings": "the settings", "calibration": "the calibration",
                   "image_a": "the first image", "image_b": "the second image",
                   "preprocess": "the preprocessing frames", "mask": "the mask files"}


def _stale_reason(job: PairJob) -> str | None:
    """Why a complete product must be recomputed for ``job`` (None: it may be kept).

    A companion file missing; a product this plenopiv cannot read (a newer schema or major
    version); one without the job's identity, or made with other settings or inputs.
    """
    from plenopiv.products.provenance import check_readable

    missing = [p.name for p in job.companions if not p.is_file()]
    if missing:
        return (f"its {', '.join(missing)} {'is' if len(missing) == 1 else 'are'} missing "
                "(deleted since it was made)")
    stored, (kind, schema, version) = _stored(job.output)
    try:
        check_readable(job.output, kind, schema, version, ValueError)
    except ValueError as exc:
        return f"this plenopiv cannot read it: {exc}"
    if job.identity is None:
        return None
    if stored is None:
        return ("the product records no identity of its settings and inputs (made by an "
                "older plenopiv or elsewhere)")
    want = dict(job.identity)
    changed = [k for k in sorted(set(want) | set(stored)) if want.get(k) != stored.get(k)]
    if not changed:
        return None
    return "made with other " + ", ".join(_IDENTITY_WORDS.get(k, k).replace("the ", "", 1)
                                          for k in changed)


def finished_before(summary_file: str | Path) -> set[str]:
    """The pairs a batch's earlier summary records as done or skipped (empty without one).

    A summary this plenopiv cannot read (a newer schema, damaged) records none.
    """
    from plenopiv.products.provenance import check_readable

    try:
        d = json.loads(Path(summary_file).read_text())
        check_readable(summary_file, "batch summary", d.get("schema_version"),
                       d.get("plenopiv_version"), ValueError)
        return {r["name"] for r in d.get("results", ())
                if r.get("status") in ("done", "skipped")}
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        return set()


def lost_reason(job: PairJob) -> str:
    """Why a pair finished before is recomputed although its product is not complete."""
    if not job.output.exists():
        return f"its product {job.output.name} was deleted since the last run"
    return f"its product {job.output.name} is no longer complete (damaged since the last run)"


def is_complete(path: str | Path) -> bool:
    """Whether ``path`` is a complete product: an HDF5 file whose root ``complete`` is true.

    A missing, unreadable or truncated file, or one without the mark, is not complete.
    """
    import h5py

    p = Path(path)
    if not p.is_file():
        return False
    try:
        with h5py.File(p, "r") as fh:
            return bool(fh.attrs.get(COMPLETE_ATTR, False))
    except Exception:  # noqa: BLE001 - any failure to read the file means "not complete"
        return False


def _remove_stale_parts(jobs: Sequence[PairJob]) -> list[Path]:
    """Delete the temporaries that a killed run left beside the jobs' products.

    :func:`plenopiv.products.files.atomic_path` names them ``.{final name}.XXXXXXXX.part`` (and a
    writer that appends a suffix, ``.part.vti``). Caught: those of the product itself, of its
    side products (``.{stem}.png...``) and of every file named after the pair
    (``.{name}_volume_A.h5...``, ``.{name}_vectors.vti...``).
    """
    removed = []
    for job in jobs:
        folder = job.output.parent
        if not folder.is_dir():
            continue
        prefixes = {glob.escape(job.output.stem), glob.escape(job.name)}
        patterns = [f".{pre}{sep}*.part{tail}" for pre in prefixes for sep in (".", "_")
                    for tail in ("", ".*")]
        for pattern in patterns:
            for p in folder.glob(pattern):
                with contextlib.suppress(FileNotFoundError):
                    p.unlink()
                    removed.append(p)
    return removed
