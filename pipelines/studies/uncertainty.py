"""Coverage of the per-vector uncertainty on the vortex validations.

The share of true errors within ±2σ, per component, on both flows, two lateral voxels, two
seedings, two camera patches and two seeds.

Every case runs the whole chain (:func:`plenopiv.workflow.vortex_case.run_case`: calibration
images -> calibration -> pair -> volumes -> 3-D PIV with the default ``[piv] uncertainty =
"response"``). The coverage is counted over the valid vectors at least half a window inside
the volume, against the flow's displacement at the window centres, for three stages of the
estimate, all from the same field:

1. correlation statistics alone (Wieneke 2015, 3-D, with the covariance of neighbouring
   voxels);
2. plus the last pass's correction (what ``[piv] uncertainty = "correlation"`` gives);
3. correlation statistics plus the error the iteration left (the geometric tail of the last
   corrections, the predictor filter's offset and the correlation's noise removed: terms
   1-2 of the default);
4. plus the chain's measured response, the deformation passes' curvature bias (less the
   curvature the vectors' random errors give it) and the range a rejected neighbour leaves
   open (:mod:`plenopiv.piv.uncertainty`), the product's default.

``python pipelines/validate_uncertainty.py --out docs/validation`` writes
``uncertainty.json``, ``uncertainty.md`` and ``uncertainty_coverage.png``.
"""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np

from pipelines.studies.output import pyplot, savefig, write_json, write_text
from plenopiv.piv.settings import PIVSettings
from plenopiv.products.vectors import VectorResult, load_vectors
from plenopiv.workflow.accuracy import gain_bias_rms
from plenopiv.workflow.compare import inner_vectors, true_displacement
from plenopiv.workflow.vortex_case import VortexCase, case_flow, coverage, run_case

#: (label, case keywords): both flows, two lateral voxels, two seedings, two patches, two seeds.
CASES = (
    ("Oseen, 41 x 61, footprint voxels", dict(flow="oseen")),
    ("Hill, 41 x 61, footprint voxels", dict(flow="hill")),
    ("Oseen, 41 x 61, half-footprint voxels", dict(flow="oseen", lateral_oversampling=2)),
    ("Hill, 41 x 61, half-footprint voxels", dict(flow="hill", lateral_oversampling=2)),
    ("Oseen, 41 x 61, half-footprint, 0.3 per lenslet",
     dict(flow="oseen", lateral_oversampling=2, particles_per_lenslet=0.3)),
    ("Hill, 41 x 61, half-footprint, 0.3 per lenslet",
     dict(flow="hill", lateral_oversampling=2, particles_per_lenslet=0.3)),
    ("Oseen, 61 x 91 patch, half-footprint",
     dict(flow="oseen", camera="auburn_50mm", lenslets=(61, 91), lateral_oversampling=2)),
    ("Hill, 61 x 91 patch, half-footprint",
     dict(flow="hill", camera="auburn_50mm", lenslets=(61, 91), lateral_oversampling=2)),
    ("Oseen, 41 x 61, footprint voxels, seed 2", dict(flow="oseen", seed=2)),
    ("Hill, 41 x 61, half-footprint, seed 2",
     dict(flow="hill", lateral_oversampling=2, seed=2)),
)
#: Configurations measured on several realisations (seeds): how far one case's coverage
#: scatters, and the coverage pooled over the realisations.
REALISATIONS = (
    ("Oseen, 41 x 61, half-footprint voxels", dict(flow="oseen", lateral_oversampling=2)),
    ("Hill, 41 x 61, half-footprint voxels", dict(flow="hill", lateral_oversampling=2)),
)
REALISATION_SEEDS = (1, 2, 3, 4, 5, 6)
#: The issue's band for the share of true errors within ±2σ.
TARGET = (0.90, 0.98)
#: Share of a Gaussian error within ±2 standard deviations, erf(sqrt(2)).
GAUSSIAN_2SIGMA = 0.9544997361036416
STAGES = ("correlation", "last_correction", "iteration", "response")
STAGE_LABELS = {"correlation": "correlation statistics",
                "last_correction": "+ last correction",
                "iteration": "statistics + iteration tail",
                "response": "+ chain response (default)"}


def evaluate_case(label: str, case: VortexCase, work: Path) -> dict:
    """Run one case; coverage per stage and component, and the errors in units of σ."""
    from plenopiv.piv import correlate_volumes
    from plenopiv.piv.uncertainty import iteration_uncertainty
    from plenopiv.products.volume import load_volume

    name = re.sub(r"[^0-9A-Za-z]+", "_", label).strip("_").lower()
    t0 = time.perf_counter()
    summary = run_case(case, work / name)
    products = summary["products"]
    va, vb = load_volume(products["volume_A"]), load_volume(products["volume_B"])
    # the PIV of the saved volumes again, for the terms of its uncertainty
    settings = PIVSettings(windows=tuple(case.windows_vox), overlap=0.5, passes=3)
    field = correlate_volumes(va.volume, vb.volume, va.grid, settings=settings)
    stored = load_vectors(products["vectors"])      # displacements, metres
    final = np.stack([getattr(stored, f"{c}_uncertainty") for c in "uvw"])
    valid = np.asarray(stored.valid, bool)
    method = stored.uncertainty_method
    scale = np.array([1.0, 1.0, abs(va.correction.scale)])[:, None, None, None]
    parts = field.uncertainty_parts
    sigma = {"correlation": parts["correlation"] * scale,
             "last_correction": np.hypot(parts["correlation"], parts["last_correction"]) * scale,
             "iteration": iteration_uncertainty(field) * scale,
             "response": final}
    vec = VectorResult.from_field(field, va.correction)
    grid = va.grid
    flow = case_flow(case, grid)
    truth = true_displacement(vec, flow, case.dt)
    ok = valid & inner_vectors(vec, grid, case.windows_vox[-1]) & np.asarray(field.valid)
    measured = np.stack([vec.u, vec.v, vec.w])[:, ok]
    err = measured - truth[:, ok]                                       # metres, physical
    vox = np.array([grid.voxel[0], grid.voxel[1], grid.voxel[2] * scale[2, 0, 0, 0]])[:, None]
    row = {"label": label, "case": dict(case.__dict__), "uncertainty_method": method,
           "n_vectors": int(ok.sum()),
           "rms_error_vox": np.sqrt(((err / vox) ** 2).mean(axis=1)).tolist(),
           "gain": gain_bias_rms(measured / vox, truth[:, ok] / vox)["gain"],
           "coverage": {}, "rms_sigma_vox": {}}
    for stage, sg in sigma.items():
        sv = sg[:, ok]
        row["coverage"][stage] = coverage(err.T, sv.T).tolist()
        row["rms_sigma_vox"][stage] = np.sqrt(np.nanmean((sv / vox) ** 2, axis=1)).tolist()
    with np.errstate(invalid="ignore", divide="ignore"):
        row["normalised_error"] = (err / sigma["response"][:, ok]).tolist()
    beside = beside_rejection(np.asarray(field.valid, bool))[ok]
    row["regions"] = region_coverage(err, sigma["response"][:, ok], beside)
    row["seconds"] = round(time.perf_counter() - t0, 1)
    return row


def beside_rejection(valid) -> np.ndarray:
    """Vectors with a rejected vector in their 3 x 3 x 3 neighbourhood, bool ``(nz, ny, nx)``.

    The neighbourhood of the median test (a rejected vector is beside itself); ``valid`` is
    the field's validation flag ``(nz, ny, nx)``.
    """
    from plenopiv.piv.uncertainty import neighbourhood_max

    return neighbourhood_max(~np.asarray(valid, bool))


def region_coverage(err, sigma, beside) -> dict:
    """Coverage and the median of |error| / σ beside a rejected vector and elsewhere.

    ``err`` and ``sigma`` ``(3, n)`` (same unit), ``beside`` ``(n,)`` bool. Per region:
    ``n``, ``coverage`` (share of |error| <= 2σ per component) and ``median_ratio``
    (median |error| / σ per component; a Gaussian error of that σ gives 0.674); NaN for an
    empty region.
    """
    err, sigma = np.asarray(err, float), np.asarray(sigma, float)
    beside = np.asarray(beside, bool)
    out = {}
    for name, mask in (("beside_rejection", beside), ("elsewhere", ~beside)):
        e, s = err[:, mask], sigma[:, mask]
        if not mask.any():
            out[name] = {"n": 0, "coverage": [np.nan] * 3, "median_ratio": [np.nan] * 3}
            continue
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.nanmedian(np.abs(e) / s, axis=1)
        out[name] = {"n": int(mask.sum()), "coverage": coverage(e.T, s.T).tolist(),
                     "median_ratio": ratio.tolist()}
    return out


def _region_table(cases) -> list[str]:
    """Coverage beside a rejected vector and elsewhere, per case (Markdown lines)."""
    cases = [c for c in cases if c.get("regions")]
    if not cases:
        return []
    lines = ["## Coverage beside a rejected vector and elsewhere", "",
             "The vectors with a vector the median test rejected in their 3 x 3 x 3 "
             "neighbourhood (where term 5 applies) apart from the others: share within ±2σ "
             "(%) and the median ratio |error| / σ (a Gaussian error of that σ gives 0.67).", "",
             "| case | beside: vectors | beside: within ±2σ u, v, w | beside: median ratio "
             "| elsewhere: vectors | elsewhere: within ±2σ u, v, w | elsewhere: median ratio "
             "|", "|---|---|---|---|---|---|---|"]
    pooled = {"beside_rejection": [np.zeros(3), 0], "elsewhere": [np.zeros(3), 0]}
    for c in cases:
        cells = [c["label"]]
        for name in ("beside_rejection", "elsewhere"):
            r = c["regions"][name]
            cells += [str(r["n"]), _f(r["coverage"], 0) if r["n"] else "–",
                      _f(r["median_ratio"]) if r["n"] else "–"]
            if r["n"]:
                pooled[name][0] += np.asarray(r["coverage"]) * r["n"]
                pooled[name][1] += r["n"]
        lines.append("| " + " | ".join(cells) + " |")
    summary = "; ".join(
        f"{label} {_f(total / n, 0)} % of {n} vectors" for label, (total, n) in
        (("beside a rejection", pooled["beside_rejection"]),
         ("elsewhere", pooled["elsewhere"])) if n)
    return lines + ["", f"Pooled over the cases (u, v, w): {summary}.", ""]


def realisation_summary(coverages, counts) -> dict:
    """Pooled coverage and scatter of one configuration over its realisations.

    ``coverages`` ``(R, 3)``: share within ±2σ per realisation and component (fractions);
    ``counts`` ``(R,)``: vectors per realisation. Returns the pooled share (vectors of every
    realisation together), the standard deviation of the realisations' shares, the binomial
    standard error one realisation of the mean size would have at the pooled share, their
    ratio, and the realisation-components outside the band.
    """
    cov = np.asarray(coverages, float)
    n = np.asarray(counts, float)
    pooled = (cov * n[:, None]).sum(axis=0) / n.sum()
    scatter = cov.std(axis=0, ddof=1) if len(cov) > 1 else np.full(3, np.nan)
    binomial = np.sqrt(pooled * (1.0 - pooled) / n.mean())
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = scatter / binomial
    outside = int(((cov < TARGET[0]) | (cov > TARGET[1])).sum())
    return {"pooled": pooled.tolist(), "n_total": int(n.sum()), "scatter": scatter.tolist(),
            "binomial": binomial.tolist(), "scatter_ratio": ratio.tolist(), "outside": outside}


def _realisations(rows, cases, work, configurations, seeds, progress) -> list[dict]:
    """Each configuration on every seed (the cases' own rows reused); its summary."""
    done = [(VortexCase(**kw), row) for (_, kw), row in zip(cases, rows, strict=True)]
    out = []
    for label, kw in configurations:
        per_seed = []
        for seed in seeds:
            case = VortexCase(**{**kw, "seed": seed})
            row = next((r for c, r in done if c == case), None)
            if row is None:
                row = evaluate_case(f"{label}, seed {seed}", case, work)
                progress(f"{label}, seed {seed}: coverage u, v, w = "
                         f"{np.round(row['coverage']['response'], 3).tolist()}")
            per_seed.append({"seed": seed, "n_vectors": row["n_vectors"],
                             "coverage": row["coverage"]["response"], "gain": row["gain"]})
        summary = realisation_summary([r["coverage"] for r in per_seed],
                                      [r["n_vectors"] for r in per_seed])
        out.append({"label": label, "seeds": per_seed, **summary})
    return out


def run(out: str | Path, *, work: str | Path | None = None, cases=CASES,
        realisations=REALISATIONS, seeds=REALISATION_SEEDS, progress=print) -> dict:
    """Run the cases; write ``uncertainty.json``, ``uncertainty.md`` and the figure to ``out``.

    Then each configuration of ``realisations`` on every seed of ``seeds``.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    work = Path(work) if work is not None else out / "uncertainty_cases"
    t0 = time.perf_counter()
    rows = []
    for label, kw in cases:
        row = evaluate_case(label, VortexCase(**kw), work)
        rows.append(row)
        progress(f"{label}: coverage u, v, w = "
                 f"{np.round(row['coverage']['response'], 3).tolist()} "
                 f"(correlation statistics alone {np.round(row['coverage']['correlation'], 3)})")
    spread = _realisations(rows, cases, work, realisations, seeds, progress)
    result = {"cases": [{k: v for k, v in r.items() if k != "normalised_error"} for r in rows],
              "realisations": spread, "target": list(TARGET),
              "seconds": round(time.perf_counter() - t0, 1)}
    write_json(out / "uncertainty.json", result, default=str)
    figure(rows, out / "uncertainty_coverage.png")
    write_text(out / "uncertainty.md", markdown(result))
    return {"json": str(out / "uncertainty.json"), "markdown": str(out / "uncertainty.md"),
            "seconds": result["seconds"]}


def figure(rows: list[dict], path: Path) -> Path:
    """Coverage per case, component and stage against the band; pooled error / σ histograms.

    The pooled distribution of error / σ is drawn per component.
    """
    plt = pyplot()
    fig = plt.figure(figsize=(14, 9), layout="constrained")
    names = [r["label"] for r in rows]
    for k, comp in enumerate("uvw"):
        ax = fig.add_subplot(2, 3, k + 1)
        y = np.arange(len(rows))
        for j, (stage, marker) in enumerate(zip(STAGES, ("o", "s", "^", "D"), strict=True)):
            ax.plot([r["coverage"][stage][k] * 100 for r in rows], y + (j - 1.5) * 0.15, marker,
                    ls="none", label=STAGE_LABELS[stage])
        ax.axvspan(TARGET[0] * 100, TARGET[1] * 100, color="g", alpha=0.15,
                   label="target 90-98 %")
        ax.set_yticks(y)
        ax.set_yticklabels(names if k == 0 else [""] * len(names), fontsize=7)
        ax.invert_yaxis()
        ax.set_xlim(0, 100)
        ax.set_xlabel("share of |error| <= 2σ (%)")
        ax.set_title(f"{comp}: coverage per case")
        if k == 2:
            ax.legend(fontsize=7, loc="lower left")
    for k, comp in enumerate("uvw"):
        ax = fig.add_subplot(2, 3, 4 + k)
        e = np.concatenate([np.asarray(r["normalised_error"][k], float) for r in rows])
        e = e[np.isfinite(e)]
        ax.hist(np.clip(e, -6, 6), bins=np.linspace(-6, 6, 61), density=True, alpha=0.7,
                label=f"{e.size} vectors, all cases")
        t = np.linspace(-6, 6, 200)
        ax.plot(t, np.exp(-t**2 / 2) / np.sqrt(2 * np.pi), "k-", lw=1, label="N(0, 1)")
        ax.axvline(-2, color="r", ls="--")
        ax.axvline(2, color="r", ls="--")
        ax.set_xlabel(f"(measured - true {comp}) / σ (clipped at ±6)")
        ax.set_title(f"{comp}: error in units of its uncertainty")
        ax.legend(fontsize=7)
    fig.suptitle("Per-vector uncertainty on the vortex validations")
    return savefig(fig, path)


def _f(v, n=2) -> str:
    return ", ".join(f"{x * 100:.0f}" if n == 0 else f"{x:.{n}f}" for x in v)


def _pct(v) -> str:
    """Fractions as percentages with one decimal, comma-separated."""
    return ", ".join(f"{x * 100:.1f}" for x in v)


def markdown(r: dict) -> str:
    """The study as Markdown."""
    cases = r["cases"]
    lines = [
        "# Per-vector uncertainty: coverage on the vortex validations (synthetic)", "",
        "Generated by `python pipelines/validate_uncertainty.py` "
        "(`pipelines.studies.uncertainty`); numbers in `uncertainty.json`, figure "
        "`uncertainty_coverage.png`.", "",
        "Coverage = share of the true errors within ±2σ (σ: the product's `u_uncertainty`, "
        "`v_uncertainty`, `w_uncertainty`), over the valid vectors at least half a window "
        "inside the volume, against the flow's displacement at the window centres. The "
        f"target is {TARGET[0]:.0%}-{TARGET[1]:.0%} per component (a Gaussian error gives "
        "95.4 %).", "",
        "## Coverage per case (%, u, v, w)", "",
        "| case | vectors | rms error u, v, w (vox) | gain u, v, w | correlation statistics | "
        "+ last correction | statistics + iteration tail | + chain response (default) | "
        "in band |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for c in cases:
        cov = c["coverage"]
        band = all(TARGET[0] <= x <= TARGET[1] for x in cov["response"])
        gain = ", ".join("–" if not np.isfinite(g) else f"{g:.2f}"
                         for g in np.asarray(c.get("gain", [np.nan] * 3), float))
        lines.append(f"| {c['label']} | {c['n_vectors']} | {_f(c['rms_error_vox'])} | {gain} | "
                     f"{_f(cov['correlation'], 0)} | {_f(cov['last_correction'], 0)} | "
                     f"{_f(cov.get('iteration', [np.nan] * 3), 0)} | "
                     f"{_f(cov['response'], 0)} | {'yes' if band else 'no'} |")
    allcov = np.array([c["coverage"]["response"] for c in cases])
    raw = np.array([c["coverage"]["correlation"] for c in cases])
    mid = np.array([c["coverage"]["last_correction"] for c in cases])
    inband = (allcov >= TARGET[0]) & (allcov <= TARGET[1])
    lines += ["", f"Mean over the cases (u, v, w): correlation statistics alone "
              f"{_f(raw.mean(axis=0), 0)} %, with the last correction "
              f"{_f(mid.mean(axis=0), 0)} %, final {_f(allcov.mean(axis=0), 0)} %; "
              f"{int(inband.sum())} of {inband.size} case-components in the band, "
              f"{int((allcov < TARGET[0]).sum())} below, {int((allcov > TARGET[1]).sum())} "
              "above.", "", _sampling_error(cases), "", *_region_table(cases),
              *_realisation_table(r.get("realisations") or []), *METHOD, "",
              f"Study time: {r['seconds']:.0f} s.", ""]
    return "\n".join(lines)


def _realisation_table(spread) -> list[str]:
    """Coverage of each configuration per seed and pooled (Markdown lines)."""
    if not spread:
        return []
    lines = ["## One configuration, several realisations", "",
             "The same configuration with other seeds (particles, noise, the response's test "
             "particles): share within ±2σ (%, u, v, w) per seed, pooled over the seeds' "
             "vectors, and the scatter of one realisation's share (standard deviation over "
             "the seeds, points) against the binomial standard error of independent "
             "vectors.", "",
             "| configuration | seed | vectors | within ±2σ u, v, w | gain u, v, w |",
             "|---|---|---|---|---|"]
    for c in spread:
        for r in c["seeds"]:
            gain = ", ".join("–" if not np.isfinite(g) else f"{g:.2f}"
                             for g in np.asarray(r["gain"], float))
            lines.append(f"| {c['label']} | {r['seed']} | {r['n_vectors']} | "
                         f"{_pct(r['coverage'])} | {gain} |")
        lines.append(f"| {c['label']} | pooled | {c['n_total']} | {_pct(c['pooled'])} | |")
    lines.append("")
    for c in spread:
        lines.append(
            f"{c['label']}: pooled {_pct(c['pooled'])} % (u, v, w); one realisation "
            f"scatters by {_pct(c['scatter'])} points, "
            f"{_f(c['scatter_ratio'], 1)} times the binomial error of independent vectors "
            f"({_pct(c['binomial'])} points); {c['outside']} of "
            f"{3 * len(c['seeds'])} seed-components outside the band.")
        lines.append("")
    return lines


def chance_outside_band(n: int, band=TARGET, coverage: float = GAUSSIAN_2SIGMA) -> float:
    """Probability that the share of ``n`` errors within ±2σ falls outside ``band``.

    For independent vectors whose errors lie within ±2σ with probability ``coverage`` (a
    Gaussian error and a σ exactly right: 95.45 %), the count within is binomial; the share
    is outside ``band`` (inclusive bounds, fractions) when the count is below
    ``ceil(band[0] n)`` or above ``floor(band[1] n)``. Dimensionless, 0-1; 1 for ``n`` = 0.
    """
    import scipy.stats

    if n <= 0:
        return 1.0
    low, high = int(np.ceil(band[0] * n - 1e-9)), int(np.floor(band[1] * n + 1e-9))
    inside = scipy.stats.binom.cdf(high, n, coverage) - scipy.stats.binom.cdf(low - 1, n, coverage)
    return float(1.0 - inside)


def _sampling_error(cases) -> str:
    """Sentences on the sampling error of the coverages.

    The binomial standard error (percentage points) and the chance that a σ exactly right
    falls outside the band.
    """
    cases = [c for c in cases if c["n_vectors"] > 0]
    if not cases:
        return ""
    se = np.array([[np.sqrt(p * (1.0 - p) / c["n_vectors"]) for p in c["coverage"]["response"]]
                   for c in cases]) * 100
    chance = np.array([chance_outside_band(c["n_vectors"]) for c in cases])
    return ("A coverage p over n vectors has the binomial standard error sqrt(p (1 - p) / n): "
            f"{se.min():.1f}-{se.max():.1f} points here (n = "
            f"{min(c['n_vectors'] for c in cases)}-{max(c['n_vectors'] for c in cases)}); the "
            "vectors of 50 %-overlapping windows are correlated, so the sampling error of "
            "each figure is larger still, and a case-component within about two of those "
            "errors of the band's edge is not told apart from it by one realisation. Even a σ "
            "exactly right, with Gaussian errors on independent vectors, falls outside the "
            f"band by chance: with probability {100 * chance.min():.1f}-"
            f"{100 * chance.max():.1f} % per case-component at these n, "
            f"{3 * chance.sum():.1f} of the {3 * len(cases)} case-components on average.")


METHOD = [
    "## Method",
    "",
    "Per vector and component the standard uncertainty is the root sum of squares of six "
    "terms (`plenopiv.piv.correlate_volumes`, `plenopiv.piv.uncertainty`):",
    "",
    "1. **Correlation statistics** (Wieneke 2015, per axis in 3-D). After the last pass the "
    "two deformed windows nearly coincide; along each axis the correlation values beside "
    "the peak are sums of per-voxel products, c+(x) = a(x) b(x + s0 + e) and "
    "c-(x) = a(x + e) b(x + s0), whose difference vanishes voxel by voxel where the windows "
    "are equal. The standard deviation of the asymmetry C+ - C- is the spread of those "
    "differences, with the covariance of neighbouring voxels counted by summing them over "
    "blocks of 2h + 1 voxels (h = the particle images' correlation width per axis, from the "
    "volume's autocorrelation); the uncertainty is the shift of the 3-point Gaussian fit for "
    "neighbours (C+ + C-)/2 ± σ/2.",
    "2. **What the iteration left.** Each deformation pass adds to the smoothed, "
    "interpolated predictor S(d) the corrector c it measures. At the iteration's fixed point "
    "the corrector is still d - S(d) (the [1, 2, 1]/4 filter's offset, about -Δ²d/4 per "
    "axis) although the estimate no longer changes: on the vortex cases this offset "
    "correlates 0.8-0.9 with the last correction (0.6-0.7 for Oseen's v, which has no "
    "motion) and is as large, so it is removed first. The "
    "passes converge geometrically, each leaving a fraction ρ of the error it starts from; "
    "the corrections then shrink by ρ per pass and what the last pass left is ρ/(1 - ρ) "
    "times the last (offset-free) correction. Each correction also holds the random error "
    "of its correlation, which does not shrink from pass to pass and which term 1 counts "
    "already: once the passes have converged the corrections are that noise alone, their "
    "ratio tends to 1 and the tail (at most 9 times the correction) counted the noise up to "
    "nine times over. So the noise is removed in quadrature: ρ² = (<c_n²> - <σ_1²>) / "
    "(<c_(n-1)²> - <σ_1²>) per component over the field (0 where the last corrections are "
    "no larger than their noise, at most 0.9; 1/2 when the previous pass had other "
    "windows), times the part of each vector's correction above its noise, "
    "sqrt(max(0, c_n² - σ_1²)). On every case here the offset-free last corrections are "
    "0.3-0.9 times the correlation statistics (rms over the field): the passes have "
    "converged to their noise and the term is 0 but for a few vectors. The previous "
    "definition, the whole last correction (ρ = 1/2 and the offset counted as error), is "
    "what `[piv] uncertainty = \"correlation\"` still gives (column \"+ last correction\").",
    "3. **The chain's response**, measured, not modelled: both reconstructions share the "
    "plenoptic camera's errors — a particle near the focal plane lights about one lenslet "
    "wherever it lies inside one footprint and one depth resolution cell, so the "
    "reconstruction does not follow it and the deformed windows match although the "
    "displacement is wrong (depth gain 0.0-0.5 near focus). Once per experiment the chain is "
    "run on ray-traced pairs of random particles (the experiment's seeding, [piv] "
    "response_particles_per_lenslet) moved by known "
    "uniform displacements — 0.5, 1.25, 1.75 lenslet footprints laterally with 0.1, 0.25, "
    "0.5 depth resolution cells in depth, then 1.25 footprints along x alone and 0.5 cells "
    "in depth alone — with the calibrated camera, the grid and every setting of the real "
    "pair, the images blurred by the point spread the calibration measured on the "
    "focal-point image (the spots' rms radius against the model's at the same stop). "
    "Per layer of vectors and test displacement this gives the gain g (mean measured / "
    "true, along the axes it moves), the spread r of the layer's vectors and the rms s of "
    "the uncertainty terms 1-2 gave those same vectors. The excess r² - s² (the spread less "
    "the random error terms 1-2 already count, so it is not counted twice) is the error both "
    "exposures share: 0 at rest, where they hold the same particles at the same places, and "
    "growing as particles cross lenslets (lateral motion) and depth cells (depth motion). "
    "Per component and layer it is fitted as a_x t_x + a_y t_y + a_z t_z (non-negative "
    "least squares over the five test pairs; t_x, t_y, t_z the motion along each axis in "
    "resolution cells; the pairs along x alone and along depth alone tell the axes apart "
    "from the diagonal ones), and a vector gets it at its own motion (held at the test "
    "pairs' largest): r_ex = sqrt(a_x t_x + a_y t_y + a_z t_z). The spread and the "
    "statistics are taken apart for the vectors on a layer's lateral edge (first or last "
    "row or column) and for its interior ones, each about the layer's mean, and each vector "
    "gets the fit of its own class: the windows that hold the volume's lateral boundary err "
    "more (particles cross it between the exposures, fewer lines of sight see its voxels; "
    "on the test pairs the edge's spread is 0.8-1.7 times the interior's). It also gets the "
    "error of a displacement measured at the chain's gain, the rms over the test pairs of "
    "|1 - g_j| / max(g_j, 0.1) times |d| (the error at the mean gain vanished where the "
    "pairs' gains lay either side of 1; `uncertainty_loo.md`); w's shared error is fitted in "
    "the lateral motion's magnitude and the depth motion, not along x and y apart. "
    "It is a type-B evaluation from a calibration of the measuring system: the vortex flows "
    "are not used to build it.",
    "4. **Unresolved curvature**: a top-hat window of edge W measures the window average, "
    "which differs from the centre value by Σ_i (W_i²/24) ∂²d/∂x_i² (second-order Taylor "
    "expansion; the uniform test displacements of term 3 cannot show it). The second "
    "derivatives are the measured field's second differences on the vector grid (with 50 % "
    "overlap the term is the second difference / 6 per axis). Deformation passes remove "
    "part of this bias: at their fixed point (trilinear predictor) the window averages of "
    "the flow's and of the predictor's curvature cancel and -(h²/12) ∂²d/∂x² remains, half "
    "of it at 50 % overlap (`tests/piv/test_uncertainty.py` iterates the fixed point), but three "
    "passes do not reach it for curvature on the scale of the vector spacing (Hill, below), "
    "so the one-window bias is kept as the bound. The curvature is the measured field's, "
    "which the windows have already flattened: where the flow curves on the scale of a "
    "window the term falls short by the chain's own loss of modulation. Three more test "
    "pairs measure it: each moves its particles by a sine of four vector spacings (two "
    "windows, the shortest wave the vector grid shows a curvature of) along a different "
    "axis per component, so that the three give every component along every axis, and the "
    "measured field's in-phase amplitude over the true one is the gain H_ka of component k "
    "along axis a (largest gradient 1/8 voxel per voxel). A wave measured at H A has the "
    "error (1 - H) A, and its second differences give the term 2 c_a H A "
    "(c_a = W_a²/(24 h_a²)); so each axis's curvature is scaled by "
    "F_ka = max(1, (1 - H_ka) / (2 c_a H_ka)), exact at that wavelength and the bound over "
    "the longer ones, where F tends to 1 (1.71 for a top-hat window at 50 % overlap; the "
    "measured H makes it 1.0-3.5, below). As term 2 no longer holds the filter's "
    "offset (about the same curvature, Δ²d/4 per axis), term 4 is added in full, less what "
    "the vectors' random errors put into it: the second differences of vectors with "
    "independent errors σ have the variance k σ², k = 2 Σ a_i² + 4 (Σ a_i)² with "
    "a_i = W_i²/(24 h_i²) (7/6 at 50 % overlap), as large as the noise itself where the "
    "field does not curve at all (Oseen's v, which is 0: term 4 was 0.02-0.03 voxel, the "
    "noise of v). That noise is terms 1 and 3's random error, counted already; term 4 is "
    "sqrt(max(0, b² - k (σ_1² + r_ex²))), with k of the scaled stencil (each a_i times "
    "F_ki) per component. At a vector on the grid's border (an axis of four or more vectors) "
    "the second difference is the one-sided 2 d_0 - 5 d_1 + 4 d_2 - d_3, the curvature at "
    "that vector (exact for a cubic, as the central one inside), not its neighbour's "
    "central one, and k is that vector's own: the square of the sum of the weights on the "
    "vector itself plus the squares of the others (the one-sided stencil carries 7.7 times "
    "the central one's noise along its axis).",
    "5. **The range a rejected neighbour leaves open.** The normalised median test rejects a "
    "vector whose measurement m disagrees with the median m~ of its 26 neighbours by more "
    "than their noise allows, and the vector is replaced by that median; the test cannot tell "
    "a spurious correlation peak from a flow that changes faster than the vector spacing "
    "resolves. Between the two readings the displacement there is known only to lie in the "
    "range D = |m - m~| per component; with nothing to prefer a value within it, the "
    "rectangular distribution over the range (GUM 4.3.7) has the standard deviation "
    "D / sqrt(12). The rejected vector and every vector of its 3 x 3 x 3 neighbourhood (the "
    "median test's, whose windows overlap its window) get it, the largest where several "
    "apply; a field without rejections gets 0. The factor 1/sqrt(12) is the GUM's, not "
    "fitted: 0.1, 0.25 and 0.5 were measured for comparison (below). The median test "
    "rejects spurious peaks too, and on term 3's uniform test pairs, whose flow the vectors "
    "resolve exactly, every rejection is one: the median S of their disagreements per "
    "component is the reach of such a peak, whose effect on its neighbours the test pairs' "
    "spread counts already, so D is counted less S in quadrature, "
    "sqrt(max(0, D² - S²)) / sqrt(12). S is the median because the disagreements are "
    "heavy-tailed: a few peaks on ghost particles 3-4 voxels off make their rms about 2 "
    "voxels along every axis while their quartiles are 0.02-0.20 voxel laterally and "
    "0.8-1.7 depth voxel (41 x 61 camera, half-footprint voxels, 76 rejected test vectors); "
    "S is 0.03-0.09 voxel laterally and 0.9-1.2 depth voxel on these cases.",
    "6. **Where the vector is.** A vector is reported at its window's centre, but its window "
    "holds the particles the reconstruction placed there; where the reconstruction places "
    "particles a distance δ from where they are, the vector is the flow's displacement at "
    "centre - δ and errs by δ · ∇d (to first order; the sensitivity coefficient of the "
    "position, GUM 5.1.3). δ is measured per axis and layer on term 3's test pairs: the "
    "volume of Gaussians of the resolution cell at the true particle positions is correlated "
    "with the reconstruction as the real pair is, window by window; the mean per layer over "
    "the five pairs is the offset, counted with the standard error of that mean. ∇d is the "
    "measured field's central differences. The uniform test displacements have no "
    "gradient, so terms 1-5 cannot see this error.",
    "",
    "## Why terms 5 and 6, the motion and the edge of term 3, the modulation of term 4",
    "",
    "- Term 4's modulation: Hill's lateral errors follow the one-window bias of the true "
    "field, which the measured field's curvature underestimates (rms ratio of the true "
    "field's term to the measured field's 1.9-2.7 for Hill's u and 1.3-1.7 for its v on the "
    "three first-seed 41 x 61 cases); with the true field's curvature in term 4 Hill's v "
    "on those cases would be covered at 93.0, 92.0 and 97.1 % (89.0, 89.0, 91.2 % with the "
    "measured field's). The measured gains at four vector "
    "spacings are H = 0.64-0.83 for u, 0.64-0.85 for v and 0.46-0.73 for w over the ten "
    "cases (the same for both flows: the chain's, not the flow's), F = 1.0-3.5. On the same "
    "fields, before term 4's border and term 5's spurious reach (next item): both changes "
    "27 of 30, without the modulation 25, without the edge split 26, "
    "without either 25 (the previous method); F = 1.71 on every axis (the top hat's "
    "instead of the measured H) 27. Over three seeds of the response's particles H "
    "scatters by about ±0.07 for u and v and ±0.15 for w (one pair per component and axis), "
    "and Hill's v on the footprint-voxel case is covered at 87.8, 89.5 and 90.1 %. Each "
    "modulation pair rendered twice with the wave a quarter period apart (half the vectors "
    "of a wave of four spacings lie near its zeros) scattered less for u and v (±0.02-0.04) "
    "and about as much for w, and gave 26 of 30 here and 98.3 % for Oseen's u on the CI "
    "camera's test: not adopted, these coverages do not tell the two apart and it costs six "
    "more reconstructions. Measured and not adopted: estimating the true "
    "curvature by deconvolving the measured field (one or two van Cittert steps of the "
    "window's bias; the noise variance of the term grows 5 and 18 times) 24 and 22 of "
    "30; the spread of the displacement inside each window from the broadening of its "
    "correlation peak over the windows' autocorrelation (Scharnowski, Hain & Kähler 2012), "
    "whose per-window estimate does not correlate with the error (r = -0.13 to +0.17, "
    "median +0.02, over the 27 components of nine cases: the widths of 12-voxel windows' "
    "peaks are too noisy).",
    "- Term 4 at the border and term 5's spurious reach: with the modulation alone (27 of "
    "30), 18 of the 21 misses of Hill's v on the footprint-voxel case lay on the first and "
    "last of the grid's four rows along y, where v was measured at about half its size in "
    "the sphere (+0.18 to +0.43 voxel against +0.50 to +0.84) and at about twice it near the "
    "volume's corners (+0.16 against +0.07), and term 4 was near 0: a border vector took its "
    "neighbour's curvature, while its window reaches half a window beyond the last vectors, "
    "where the flow curves on. The one-sided stencil brings that case to 92.4 %, but alone "
    "it gives 26 of 30: Hill's w goes over the band (100.0, 98.2, 99.2 % on the second seed, "
    "half-footprint voxels and the patch), where term 5 was already two to three times the "
    "w error. Term 5 counts the rejected vectors' disagreements as unresolved flow, and for "
    "Hill's w they are not: its rejected vectors disagree in depth as much as the uniform "
    "test pairs' spurious peaks do (medians 0.71 and 1.1 depth voxels on the half-footprint "
    "case), laterally 2-26 times more (u 2.1 voxels against 0.08, v 0.2 against 0.09), where "
    "its core reverses within a window. On the test pairs the vectors beside a rejected one "
    "spread 1.3-3.8 times more than the others (u 3.9-6.5 µm against 1.5-2.8 µm; w 37-63 "
    "against 12-38 µm) but far less than the peaks' range D / sqrt(12) (rms up to 68 µm for "
    "u): a spurious peak does not carry its range to its neighbours. On the same fields: "
    "both changes 29 of 30, the border alone 26, the spurious reach alone 27, neither 27; "
    "with the rms of the test pairs' disagreements instead of their median (about 2 voxels "
    "along every axis, set by a few peaks on ghost particles) 27, Hill's v at 86.5-89.5 %. "
    "Measured and not adopted: the range capped by the spread of the rejected vector's valid "
    "neighbours (max - min per component), or that spread alone, 25 and 23 of 30 (Hill's w "
    "stays over, Hill's u on half-footprint voxels falls to 87.7 %).",
    "- Term 6: on the volume from Z = 0.5 to 8.5 mm of `vortex.md` (61 x 91-lenslet patch of "
    "the Auburn camera, 10.4 mm substrate) Oseen's u was covered at 80.0 %. Its error was an "
    "offset of +0.06 to +0.13 voxel in the layers where u changes sign across the vortex's "
    "centre depth (measured u -1.10, +0.06, +1.20 against true -1.24, -0.10, +1.07 at "
    "Z = 3.7, 4.4, 5.2 mm), not a gain. The flow evaluated 0.1 mm deeper than the vectors' "
    "nominal depth removes it (u rms 0.088 -> 0.052 voxel), and the reconstructed particles "
    "lie short of their true depth: by 46 to 133 µm from Z = 1.2 to 7.6 mm (median over about "
    "140 matched particles per band; +5 to -64 µm over ±3.2 mm with the same patch centred on "
    "focus, under 20 µm on the CI camera, which has no substrate). The correlation of the true "
    "particles' volume with the reconstruction gives the same, -0.39 to -1.08 depth voxel, "
    "within 15 % with Gaussians half or twice the resolution cell. Of that, the sharp "
    "rendering of the same particles gives -0.28 to -0.77 voxel (the calibrated camera or "
    "the true one alike, Poisson noise changing nothing) and the 0.5 px point spread of the "
    "rendering the rest: so the response renders its test pairs with the point spread the "
    "calibration measures (0.46 px here, the effective width of the study's sampled 0.5 px "
    "kernel). With term 6, Oseen's u on that volume is covered at 94.8 % (its v and w at 91.6 "
    "and 91.9 %).",
    "- Term 3 per axis of motion: the lateral-only test pair moved along x and y at once; "
    "moved along x alone it shows that a lateral component's shared error follows the motion "
    "along its own axis: from 1.25 footprints along x, v's excess is 0.00-0.02 voxel per layer "
    "against 0.00-0.13 from the diagonal pairs, u's 0.00-0.16 against 0.00-0.16 (every case "
    "here). Counting the lateral motion whatever its direction gave Oseen's v (0, its "
    "particles moving along x and z) the error of the diagonal pairs' motion along y: 98.8-99.4 "
    "% on the patch cases of `vortex.md`, 94.1-96.7 % now. Here, on the same test pairs, the "
    "per-axis fit and the lateral motion as a whole give 25 of 30 either way (Oseen's v on the "
    "footprint-voxel case 97.3 -> 95.2 %, Hill's 89.5 -> 89.0 %); the per-axis fit is kept "
    "because it is what the test pairs measure.",
    "- Before term 5, Hill's lateral components were under-covered (u 69-83 %, v 70-86 % on "
    "the 41 x 61 camera) and the misses gathered beside vectors the median test had rejected "
    "(61-84 % of the u errors within ±2σ there, 86-94 % elsewhere). Hill's core reverses u "
    "within about one last-pass window (the true u runs from -1.3 footprints outside to "
    "+1.8 at the centre over about two vector spacings); the rejected vectors are largely the "
    "ones that saw the reversal. Correlating the last pass with the test switched off, 15-24 "
    "of the 33-61 vectors the test flags on each Hill case lie within one voxel of the truth "
    "(3-18 of 7-48 on Oseen), and the median that replaces them does not: over all vectors "
    "inside the volume Hill's u rms is 0.68, 1.59, 1.58, 0.55 and 1.25 voxels against "
    "0.36, 0.81, 0.86, 0.37 and 0.57 over the valid ones. Their valid neighbours, whose "
    "windows overlap theirs, carry errors of the same order that no other term sees. "
    "With term 5 (and term 3 by motion, next items) Hill's u is covered at 93.6-98.1 % and "
    "its v at 89.0-94.2 %.",
    "- Measured alternatives to term 5 (with the per-layer excess of term 3, where term 5 "
    "gave 19 of 30): the factor 0.1, 0.25 or 0.5 instead of 1/sqrt(12) 18, 19, 19 of 30; "
    "face neighbours only 15; the range less the rejected vector's random error (its "
    "variance once or four times; with the excess in the whole motion) 22 and 24 of 30 — "
    "not adopted, the factor would be chosen on these cases; instead of term 5, the local "
    "standard "
    "deviation of the measured field, the median residual of each vector or the "
    "neighbourhood's largest term 4: 9-13 of 30, over-covering Oseen's u, whose linear "
    "gradients they count although the deformed windows follow them.",
    "- Measuring Hill's core instead was tried on the saved volumes: a median threshold of 3 "
    "instead of 2 (Hill's u rms over all vectors 0.56, 1.50, 1.51, 0.47, 0.88 voxel; Oseen's "
    "w worse, 0.36 -> 0.45 on the patch); no test (Oseen's u 0.51 and 0.76 voxel: the test is "
    "needed); testing each pass's corrector instead of the displacement, or keeping a "
    "flagged vector whose peak ratio is at least 1.5 or 2: Hill's u about unchanged (0.49-1.65). "
    "Windows of 12 footprints and more hold both populations of particles, and their peak "
    "follows the larger one: starting the passes at 12 instead of 16 footprints leaves "
    "Hill's u as it is (0.68, 1.58, 1.55, 0.53, 1.17 voxels), while last windows of 8 "
    "footprints resolve the core (u gain 0.65, 0.64, 0.89 against 0.21, 0.11, 0.80 on the "
    "footprint-voxel, 0.3-per-lenslet and patch cases) but reject 16-20 % of the vectors at "
    "these seedings. Not changed.",
    "- Term 3's excess was the mean over the test displacements, the same for every vector of "
    "a layer: Oseen's v (which is 0) and Hill's w were over-covered, the test pairs moving "
    "more than those vectors. Interpolated in each component's own displacement it "
    "under-covered Oseen's v (80-88 %): v is 0, but its particles move in u and w and change "
    "lenslets and depth cells all the same. Interpolated in the vector's whole motion through "
    "the three diagonal test pairs it gave 23 of 30 (19 with the mean); but those pairs move "
    "about five times more laterally than in depth (in resolution cells) and cannot say "
    "which motion the shared error follows. The two pairs that move one way only (measured "
    "on the footprint-voxel Oseen case) answer it: lateral motion alone gives w an excess as "
    "large as the diagonal pairs' (0.14-0.55 depth voxel per layer, against 0.08-0.76), depth "
    "motion alone gives u almost none (0.01-0.02 voxel, against 0.00-0.11). With them and "
    "the additive fit, 27 of 30 (with the lateral pair moving along x and y at once, before "
    "the per-axis fit and term 6 of the first items).",
    "",
    "## What is not met",
    "",
    "- Hill's u on the second seed, 98.1 %: 158 of 161 vectors within ±2σ, one vector over "
    "the band (97.5 % with one more miss; binomial standard error 1.1 points). Its σ is "
    "dominated by term 5 (rms 0.50 voxel) and term 4 (0.44 voxel, against 0.11 on the "
    "first seed with the same response: H and F are the same to ±0.03, its measured field "
    "curves more) against an rms error of 0.28 voxel; without term 4 it would be 96.3 %. "
    "Nothing here is tuned to move it. The first seed measures Hill's core as the flow "
    "around it (u -1.9 to -2.9 voxels on the three middle layers where it is +1.1 to +3.6, "
    "most of those vectors rejected and replaced); on the second four core vectors are "
    "measured near the truth (+3.5, +3.1, +1.9, +1.8 against +3.6, +2.8, +2.3, +1.6) and "
    "pass the median test, and the curvature they make is what raises term 4.",
    "- Where that σ is too large (the table above). Beside a rejected vector u, v, w are "
    "covered at 98, 96, 96 % pooled (1426 vectors; 92-100 % per case-component), elsewhere "
    "at 91, 93, 95 % (959; 80-100 %); beside a rejection the median |error|/σ is 0.20-0.46 "
    "(u), 0.20-0.68 (v), 0.31-0.77 (w) where a Gaussian error of that σ gives 0.67. Term 5 "
    "gives every vector of the neighbourhood the whole range, which bounds the few whose "
    "windows saw the unresolved flow and overstates the rest; and a rectangular "
    "distribution lies wholly within ±2σ (2/sqrt(12) = 0.58 of its width on either side). "
    "The totals land in the band because the two regions err in opposite directions; a case "
    "whose vectors mostly sit beside rejections (Hill's second seed: 126 of 161) shows the "
    "first. Measured on the saved fields and not adopted: the range weighted by the window "
    "overlap with the rejected vector (1/2 per axis of offset, 23 of 30; its square root, 29 "
    "with Hill's v at 0.3 per lenslet at 88.2 %), term 4 without the replaced vectors (25), "
    "each neighbour's own random error in term 4's noise (26), the larger of terms 4 and 5 "
    "instead of their quadrature sum (29, unchanged), term 4's squared estimate averaged "
    "over the 7 or 27 nearest vectors (26, 22: Hill's core spreads). What would close it: "
    "telling, among a rejected vector's neighbours, the ones whose windows hold the "
    "unresolved flow (for instance from their own residual to the median, whose rank "
    "correlation with the error is 0.4-0.5 on Hill), measured on test pairs with a resolved "
    "feature rather than on these cases. The plain form of that idea, each neighbour's range "
    "cut to its own disagreement with its neighbours' median, gave 19 of 30 (Hill's u 77-87 "
    "%): a neighbour of a rejected vector agrees with its neighbours because they saw the "
    "same flow.",
    "- One realisation is not a measurement of the coverage (the section on realisations "
    "above): two configurations on six seeds each scatter by 2.6-4.3 points per "
    "component (Hill's w 0.8), 1.5-2.4 times the binomial error (the vectors of "
    "overlapping windows are correlated), and 9 of their 36 seed-components fall outside "
    "the band, on both "
    "sides, while the coverage pooled over the seeds is in the band for every component "
    "(Oseen 92.3, 93.8, 93.1 %; Hill 96.7, 94.7, 95.9 %). Hill's u is the highest pooled "
    "figure, 1.3 points below the band's top: that σ is conservative there, as the split "
    "above says, and about half of Hill's realisations go over on u or v.",
    "- This table counts a window touching a face of the volume as inside (a millionth "
    "of a voxel of rounding allowed, `plenopiv.workflow.compare.inner_vectors`); before, "
    "the patch's outer layers, exactly half a window in, were kept or dropped by float "
    "rounding (Hill's patch 396 vectors instead of 473, its w 98.7 % instead of 97.5 %; the "
    "counts of the item on term 4's border and term 5's reach above are on 473).",
    "- The predictor's filter is not the cause of Hill's lateral error. The [1, 2, 1]/4 "
    "filter applied to the predictor before every deformation pass widens the spatial filter "
    "beyond one window (Schrijer & Scarano 2008). Measured on six cases (Oseen and Hill, "
    "footprint and half-footprint voxels, seed 1; Oseen footprint and Hill half-footprint "
    "voxels, seed 2), rms error u, v, w in voxels with the filter on every pass -> filtering "
    "only the predictor of the pass whose window shrinks -> no filter -> a [1, 6, 1]/8 filter "
    "before the passes at the final window: Hill footprint voxels u 0.36 -> 0.32 -> 0.35 -> "
    "0.36 (gain 0.42 -> 0.47 -> 0.46 -> 0.41), half-footprint 0.81 -> 0.80 -> 0.83 -> 0.80 "
    "(gain 0.28 in all four), seed 2 0.57 -> 0.51 -> 0.51 -> 0.49; Oseen u 0.13, 0.22, 0.12 "
    "-> 0.15, 0.30, 0.14 -> 0.17, 0.36, 0.14 -> 0.13, 0.25, 0.13 and w 0.43, 0.44, 0.53 -> "
    "0.49, 0.53, 0.59 -> 0.49, 0.50, 0.61 -> 0.41, 0.48, 0.55. The filter stays on every "
    "pass (`[piv] smooth_predictor`).",
    "- Hill's lateral gains stay low on the 41 x 61 camera (u 0.28-0.75): the windows do not "
    "resolve the core. More vectors across it would: on the 61 x 91-lenslet patch Hill's u "
    "and v gains are 0.89 and 0.94, and last windows of 8 footprints raise them (above) "
    "where the seeding allows.",
    "- Near focus the true depth displacement of Oseen's vortex is 1-2 voxels where the "
    "measured one is 0.3-0.6: the gain term scales the measured value, and where the chain "
    "sees almost nothing the bound stays short.",
    "- `plenopiv piv` on two volume products has no calibration and images: it gives terms 1 "
    "and 2 in their previous form only (`uncertainty_method = \"correlation\"` in the "
    "product).",
]
