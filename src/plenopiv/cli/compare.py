"""``plenopiv compare``: a vectors product against the truth (a simulated pair, or vectors)."""

from __future__ import annotations

import math

from plenopiv.cli._common import _add_common, _add_example, _integer

#: Most depth bands ``--bands`` takes.
MAX_BANDS = 100


def add_parser(sub) -> None:
    """Add ``compare`` to the subcommands ``sub``."""
    p = sub.add_parser(
        "compare", help="gain, bias and rms of a vectors product against the truth",
        description="Compare a vectors product (plenopiv piv or plenopiv run) with the truth: "
        "a synthetic pair (plenopiv simulate pair), whose recorded flow is evaluated at the "
        "window centres (or, where it cannot be rebuilt, its true particle displacements "
        "averaged over each window), or another vectors product on the same grid. Per "
        "component u, v, w: the gain (least-squares slope of measured on true), bias, rms "
        "error, correlation coefficient and true rms, in voxels of the product's grid and in "
        "metres, over the valid vectors whose window lies inside the volume, overall and in "
        "equal bands of depth Z.")
    p.add_argument("vectors", help="vectors product (.h5 of plenopiv piv or plenopiv run)")
    p.add_argument("truth", help="synthetic pair (.h5 of plenopiv simulate pair) or a vectors "
                   "product on the same grid")
    p.add_argument("--bands", type=int, default=3,
                   help="equal bands of depth Z for the figures per depth (default 3)")
    _add_common(p)
    _add_example(p, "plenopiv compare vectors.h5 pair.h5 --bands 3")
    p.set_defaults(func=cmd_compare)


def cmd_compare(args) -> dict:
    """Gain, bias, rms and correlation of a vectors product against the truth."""
    from plenopiv.workflow.compare import compare_products

    _integer("--bands", args.bands, minimum=1, maximum=MAX_BANDS)
    return {"command": "compare",
            **compare_products(args.vectors, args.truth, bands=args.bands)}


def _number(value, spec: str) -> str:
    return "-" if value is None or not math.isfinite(value) else format(value, spec)


#: The columns of the table: (header, key, format, scale to the unit of the header).
COLUMNS = (("gain", "gain", ".3f", 1.0), ("bias vox", "bias", "+.3f", 1.0),
           ("rms vox", "rms", ".3f", 1.0), ("r", "correlation", ".3f", 1.0),
           ("true rms vox", "true_rms", ".3f", 1.0), ("bias mm", "bias_m", "+.5f", 1e3),
           ("rms mm", "rms_m", ".5f", 1e3), ("true rms mm", "true_rms_m", ".5f", 1e3))


def accuracy_lines(acc: dict) -> list[str]:
    """The figures of a comparison (:func:`plenopiv.workflow.compare.field_accuracy`) as a table.

    One row per component for all the vectors, then per depth band; the notes below.
    """
    header = ["", *(c[0] for c in COLUMNS)]
    rows = [header]
    blocks = [("all", acc["n_vectors"], acc["overall"])]
    blocks += [(f"Z {b['z_m'][0] * 1e3:.3f} to {b['z_m'][1] * 1e3:.3f} mm", b["n_vectors"], b)
               for b in acc.get("bands", [])]
    titles = {}
    for title, n, figs in blocks:
        titles[len(rows)] = f"{title} ({n} vectors)"
        for comp in ("u", "v", "w"):
            f = figs[comp]
            rows.append([f"  {comp}", *(_number(None if f[key] is None else f[key] * s, spec)
                                        for _, key, spec, s in COLUMNS)])
    width = [max(len(r[i]) for r in rows) for i in range(len(header))]
    lines = []
    for i, r in enumerate(rows):
        if i in titles:
            lines.append(titles[i])
        lines.append("  ".join([r[0].ljust(width[0])] + [c.rjust(w) for c, w in
                                                          zip(r[1:], width[1:], strict=True)]))
    notes = acc.get("notes", [])
    if notes:
        lines.append("notes:")
        lines += [f"  {n}" for n in notes]
    return lines


def print_summary(s: dict) -> None:
    """``plenopiv compare``: what was compared, then the table (:func:`accuracy_lines`)."""
    vox = " x ".join(f"{v * 1e3:.4g}" for v in s["voxel_m"])
    print(f"vectors: {s['vectors']}")
    print(f"truth:   {s['truth']} ({s['truth_kind']}; truth at the vectors: "
          f"{s['truth_at_vectors']})")
    print(f"voxel:   {vox} mm (x, y, z)")
    print("gain: least-squares slope of measured on true; r: correlation coefficient")
    for line in accuracy_lines(s):
        print(line)
