"""What each product of an experiment records of its origin, and what its consumers check.

The records are :func:`~plenopiv.products.provenance.make_provenance`'s: a volume records its
image, the calibration file, the ``[mask]`` files and the preprocessing frames (content
hashes) and the tables that shaped it (:data:`VOLUME_SETTINGS`); a vectors product its two
volume files and their records; a tracks product its images and the products it reused.
:func:`check_volume_pair` (``plenopiv piv``) and :func:`check_track_products`
(``plenopiv track``) refuse products of other origins, naming both files and what differs
(:class:`~plenopiv.errors.ProvenanceError`).
"""

from __future__ import annotations

from collections.abc import Mapping

from plenopiv.errors import ProvenanceError
from plenopiv.products.files import file_identity
from plenopiv.products.provenance import (
    differences,
    json_hash,
    make_provenance,
    mismatched_inputs,
    short,
)

__all__ = ["VOLUME_SETTINGS", "check_track_products", "check_volume_pair", "frame_inputs",
           "mask_inputs", "settings_hashes", "tracks_provenance", "vectors_provenance",
           "volume_provenance"]

#: The settings that shape a volume: the camera and these experiment tables.
VOLUME_SETTINGS = ("camera", "volume", "reconstruction", "particles", "preprocess", "mask")
#: The settings a vectors product adds to its volumes'.
VECTORS_SETTINGS = ("piv", "dt_s")
#: The settings that shape a tracks product.
TRACKS_SETTINGS = VOLUME_SETTINGS + ("piv", "tracking", "dt_s")
#: What two volumes correlated together must share: every input but the image, every
#: setting but the particle table (their particles are not correlated).
PAIR_IGNORES = ("image", "particles")


def settings_hashes(experiment, names=VOLUME_SETTINGS) -> dict[str, str]:
    """``{name: json_hash}`` of the experiment's tables ``names`` (``dt_s``: ``[images]``'s)."""
    d = experiment.to_dict()
    d["dt_s"] = d["images"].get("dt_s")
    return {name: json_hash(d.get(name)) for name in names}


def mask_inputs(experiment) -> dict[str, str]:
    """Content hashes of the ``[mask]`` files: ``mask_image``, ``mask_volume``."""
    m = experiment.mask
    if m is None:
        return {}
    return {f"mask_{k}": file_identity(experiment.path(v))
            for k, v in (("image", m.image), ("volume", m.volume)) if v is not None}


def frame_inputs(record: Mapping | None) -> dict[str, str]:
    """Content hashes of the preprocessing frames of a ``preprocess`` record."""
    out = {}
    for name in ("dark", "white", "background"):
        entry = (record or {}).get(name)
        if isinstance(entry, Mapping) and entry.get("sha256"):
            out[name] = entry["sha256"]
    return out


def volume_provenance(experiment, *, image: str, calibration: str, record=None,
                      masks: Mapping | None = None) -> dict:
    """The record of a volume: its image and calibration (content hashes), masks, frames.

    ``image``, ``calibration``: the hashes (:func:`~plenopiv.products.files.file_identity`);
    ``masks``: :func:`mask_inputs` when known already.
    """
    inputs = {"image": image, "calibration": calibration,
              **(mask_inputs(experiment) if masks is None else masks), **frame_inputs(record)}
    return make_provenance("volume", inputs=inputs,
                           settings=settings_hashes(experiment, VOLUME_SETTINGS))


def vectors_provenance(volume_a, volume_b, *, piv, dt, sources: Mapping) -> dict:
    """The record of a vectors product made from the volume files ``volume_a``, ``volume_b``.

    ``piv``: the PIV settings (:class:`~plenopiv.piv.settings.PIVSettings`); ``sources``:
    the volumes' own records.
    """
    from plenopiv.settings import as_dict

    return make_provenance("vectors", inputs={"volume_a": file_identity(volume_a),
                                              "volume_b": file_identity(volume_b)},
                           settings={"piv": json_hash(as_dict(piv)), "dt_s": json_hash(dt)},
                           sources={k: sources.get(k) for k in ("volume_a", "volume_b")})


def tracks_provenance(experiment, *, inputs: Mapping, sources: Mapping | None = None,
                      record=None) -> dict:
    """The record of a tracks product: ``inputs`` (hashes), the masks, the frames, sources."""
    return make_provenance("tracks",
                           inputs={**inputs, **mask_inputs(experiment), **frame_inputs(record)},
                           settings=settings_hashes(experiment, TRACKS_SETTINGS),
                           sources=sources)


def check_volume_pair(path_a, record_a: Mapping, path_b, record_b: Mapping) -> None:
    """Refuse two volumes to be correlated that were not made alike, naming both files.

    Every input but the image (calibration, masks, preprocessing frames) and every setting
    but the particle table must agree; what either does not record is not compared.
    """
    diffs = differences(record_a, record_b, ignore=PAIR_IGNORES)
    if diffs:
        raise ProvenanceError(
            f"the volumes {str(path_a)!r} and {str(path_b)!r} were not made alike: they "
            f"differ in their {'; '.join(diffs)}. Reconstruct both exposures with the same "
            "calibration, camera and experiment settings (only the image may differ)")


def _recorded(record: Mapping, role: str, tag: str) -> str | None:
    """The hash of ``role`` (``image`` or ``calibration``) for exposure ``tag`` ("a", "b").

    Held by the record itself (a tracks product or its binned field: ``image_a``,
    ``calibration``), or by its volume's record (a vectors product: ``image``).
    """
    inputs = record.get("inputs") or {}
    key = f"image_{tag}" if role == "image" else role
    if key in inputs:
        return inputs[key]
    source = (record.get("sources") or {}).get(f"volume_{tag}") or {}
    return (source.get("inputs") or {}).get(role)


def check_track_products(given: Mapping[str, tuple], *, images: tuple, calibration: tuple,
                         settings: Mapping[str, str]) -> None:
    """Refuse products reused by ``plenopiv track`` that were made from another pair.

    ``given``: role (``volume_a``, ``volume_b``, ``vectors``) -> ``(the file as named,
    its record)``; ``images``: ``((hash, name) of A, (hash, name) of B)``; ``calibration``:
    ``(hash, name)``; ``settings``: :func:`settings_hashes` of the experiment. A volume must
    be of its image and of the calibration, on the experiment's camera, grid and
    reconstruction; the vectors of the volumes given (their files) or of the images.
    """
    problems = []
    for tag, (digest, name) in zip("ab", images, strict=True):
        if f"volume_{tag}" not in given:
            continue
        shown, record = given[f"volume_{tag}"]
        wrong = mismatched_inputs(record, {"image": (digest, name), "calibration": calibration})
        wrong += differences(record, {"settings": settings}, sections=("settings",),
                             ignore=("particles", "preprocess", "mask"),
                             form="its {word} is not the experiment's ({a} ≠ {b})")
        problems += [f"--volume-{tag} {str(shown)!r}: {w}" for w in wrong]
    if "vectors" in given:
        shown, record = given["vectors"]
        expected = {f"volume_{t}": (file_identity(given[f"volume_{t}"][0]),
                                    str(given[f"volume_{t}"][0]))
                    for t in "ab" if f"volume_{t}" in given}
        wrong = mismatched_inputs(record, expected)
        for tag, (digest, name) in zip("ab", images, strict=True):
            made = _recorded(record, "image", tag)
            if f"volume_{tag}" not in given and made is not None and made != digest:
                wrong.append(f"its {'first' if tag == 'a' else 'second'} image is "
                             f"{short(made)}, not {name!r} ({short(digest)})")
        made = _recorded(record, "calibration", "a")
        if made is not None and made != calibration[0]:
            wrong.append(f"its calibration file is {short(made)}, not {calibration[1]!r} "
                         f"({short(calibration[0])})")
        problems += [f"--vectors {str(shown)!r}: {w}" for w in wrong]
    if problems:
        raise ProvenanceError("products of another pair or calibration given to plenopiv "
                              f"track: {'; '.join(problems)}. Give the products made from "
                              "these images and this calibration, or leave them out to make "
                              "them again")
