"""`vdo validate`: the run folder of a validation (`vdo.dic.validate.run_cases` computes it, this
module decides what to write) and the console table.

The run folder (atomic, `vdo.core.runfolder`: appears whole or not at all):

    validation.csv     per case and axis: predicted, measured, ratio, n_seeds (+ diagnostics);
                       a '#' comment line states the convention
                       (strain cases: the strain components, in microstrain, `unit` column)
    validation.png     measured against √2 x predicted sigma, log-log, the [0.8, 1.25] band
                       (validation_strain.png: the same for the strain cases)
    estimates.csv      every measured U (µm) per case and seed (estimates_strain.csv: strains)
    summary.json       the convention, per-case diagnostics (noise-free errors, speckle and shift in
                       pixels, times), wall time, the verdicts' counts, pass/fail
    images/<case>.png  the noise-free reference image of each camera
    validation.toml    a copy of the validation file
    report.html        the run's page (`vdo.outputs.html_report`)
"""

from __future__ import annotations

import csv
import json
import math
import shutil

import numpy as np

from vdo.dic.verdicts import BAND, CONFIDENCE, seeds_to_decide
from vdo.dic.validate import (STRAIN_AXES, UM, ValidationResult, ValidationSpec,
                              noise_free_images, run_cases)

CSV_FIELDS = ["case", "axis", "sigma_predicted_um", "sigma_measured_um", "ratio", "n_seeds",
              "sigma_expected_um", "ratio_ci95_low", "ratio_ci95_high", "bias_um", "rms_error_um",
              "sigma_linear_um", "unit", "processing", "sigma_predicted_all_views_um",
              "ratio_joint_low", "ratio_joint_high", "verdict", "seeds_to_decide"]
CONVENTION = ("sigma_predicted_um: vdo.physics.predict, the Cramer-Rao bound for ONE noisy image against a "
              "noise-free reference, for the correlated patch. sigma_measured_um: standard "
              "deviation over the seeds of the correlated displacement, reference and deformed "
              "images both noisy (reference='images'). sigma_expected_um = sqrt(2) * "
              "sigma_predicted_um. ratio = sigma_measured_um / sigma_expected_um (1 when the model "
              "is right; the requirement is [0.8, 1.25]). ratio_ci95_*: the 95% interval of the "
              "ratio from the seed count alone (chi-square, n_seeds - 1 degrees of freedom). "
              "ratio_joint_*: the interval at 95% confidence jointly over the run's ratios "
              "(Bonferroni); verdict: within (it lies inside [0.8, 1.25]), outside (wholly outside: "
              "the run fails) or inconclusive (it holds a band edge: too few seeds to tell; "
              "seeds_to_decide: the seeds that would decide it at the same ratio). bias_um: mean "
              "error (measured - imposed). "
              "rms_error_um: rms error about the imposed displacement. sigma_linear_um: the "
              "correlation's own linear noise propagation (CorrelationResult.covariance) at the "
              "modelled noise level, on the noise-free images. Strain cases (a homogeneous strain imposed "
              "on the plate, Q4 correlation): axis eps_uu, eps_vv, eps_uv (tensor shear, face "
              "frame) at the centre of the middle element, vdo.physics.strain's prediction, and the *_um "
              "columns in microstrain (unit column). processing: all-views (one correlation over "
              "every camera) or pairs (best|fusion): each stereo pair correlated on its own and the "
              "pairs' displacements merged as vdo.physics.measured.pair_merge defines it; "
              "sigma_predicted_um is then the bound of the merged displacement "
              "(vdo.physics.measured.merge_pairs) and sigma_predicted_all_views_um the all-views "
              "bound of the same cameras (equal to sigma_predicted_um for all-views cases).")



def validate_cases(spec: ValidationSpec, out, seeds: int | None = None, overwrite: bool = False,
                   cases: list[str] | None = None) -> dict:
    """Run every case of `spec` (or those named in `cases`) with `seeds` seeds (default: the
    file's; `vdo.dic.validate.run_cases`) and write the run folder `out` (module docstring); the
    output folder is checked before any work. Returns the summary.json dict."""
    from vdo.core.runfolder import check_out

    check_out(out, overwrite)
    return write_validation(run_cases(spec, seeds, cases), out, overwrite)


def write_validation(result: ValidationResult, out, overwrite: bool = False) -> dict:
    """Write a `ValidationResult` into the run folder `out` (module docstring); returns the
    summary.json dict."""
    from vdo.outputs import html_report
    from vdo.commands.render import contact_sheet
    from vdo.core.runfolder import inside, run_folder

    spec, seeds, rows = result.spec, result.seeds, result.rows
    with run_folder(out, overwrite) as tmp:
        (tmp / "images").mkdir()
        for case in result.cases:
            setup = case.setup
            contact_sheet({c.name: np.rint(im).astype(np.int64) for c, im in
                           zip(setup.cameras, noise_free_images(setup, False))},
                          setup.case.sensor.max_dn, inside(tmp / "images", f"{setup.case.name}.png"),
                          f"{setup.case.name}: noise-free reference")
        write_csv(rows, tmp / "validation.csv")
        displacement = [c for c in result.cases if c.setup.case.strain is None]
        strained = [c for c in result.cases if c.setup.case.strain is not None]
        with open(tmp / "estimates.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["case", "seed", "Ux_um", "Uy_um", "Uz_um"])
            for case in displacement:
                for k, u in enumerate(case.estimates):
                    w.writerow([case.setup.case.name, k, *(f"{v * UM:.6g}" for v in u)])
        if strained:
            with open(tmp / "estimates_strain.csv", "w", newline="") as fh:
                w = csv.writer(fh)
                w.writerow(["case", "seed", *(f"{a}_microstrain" for a in STRAIN_AXES)])
                for case in strained:
                    for k, e in enumerate(case.estimates):
                        w.writerow([case.setup.case.name, k, *(f"{v * 1e6:.6g}" for v in e)])
        for suffix, kind in (("", "um"), ("_strain", "microstrain")):
            chosen_rows = [r for r in rows if r["unit"] == kind]
            if chosen_rows:
                plot(chosen_rows, tmp / f"validation{suffix}.png",
                     f"{spec.name}: {seeds} seeds per case" + (" (strain)" if suffix else ""))
        shutil.copyfile(spec.path, tmp / "validation.toml")
        summary = {"name": spec.name, "config": str(spec.path), "seeds": seeds,
                   "convention": CONVENTION, "band": list(BAND), "confidence": CONFIDENCE,
                   "verdicts": result.verdicts, "passed": result.passed,
                   "noise_free_passed": result.noise_free_passed,
                   "wall_seconds": round(result.wall_seconds, 1),
                   "cases": [c.info for c in result.cases],
                   "rows": [{k: ((round(v, 6) if math.isfinite(v) else None) if isinstance(v, float)
                             else v) for k, v in r.items()}
                            for r in rows]}
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        html_report.write_report(tmp)
    return summary


def plot(rows: list[dict], path, title: str = "") -> None:
    """Measured against expected (√2 x predicted) sigma, log-log, y = x and the [0.8, 1.25] band."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 5.6), layout="constrained")
    x = np.array([r["sigma_expected_um"] for r in rows])
    y = np.array([r["sigma_measured_um"] for r in rows])
    lo, hi = min(x.min(), y.min()) / 1.6, max(x.max(), y.max()) * 1.6
    line = np.geomspace(lo, hi, 50)
    ax.fill_between(line, BAND[0] * line, BAND[1] * line, color="0.88", label="ratio in [0.8, 1.25]")
    ax.plot(line, line, "k-", lw=1, label="measured = √2 predicted")
    cases = list(dict.fromkeys(r["case"] for r in rows))
    colors = plt.get_cmap("tab10")
    markers = {"x": "o", "y": "s", "z": "^", "eps_uu": "D", "eps_vv": "v", "eps_uv": "<"}
    unit = "µε" if rows[0].get("unit") == "microstrain" else "µm"
    for r in rows:
        ci = cases.index(r["case"])
        err = [[r["sigma_measured_um"] * (1 - r["ratio_ci95_low"] / r["ratio"])],
               [r["sigma_measured_um"] * (r["ratio_ci95_high"] / r["ratio"] - 1)]]
        ax.errorbar(r["sigma_expected_um"], r["sigma_measured_um"], yerr=err, fmt=markers[r["axis"]],
                    color=colors(ci % 10), ms=6, capsize=2,
                    label=f"{r['case']} {r['axis']}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(lo, hi)
    ax.set_ylim(lo, hi)
    ax.set_xlabel(f"expected σ = √2 × predicted ({unit})  [both images noisy]")
    ax.set_ylabel(f"measured σ over seeds ({unit})")
    ax.set_title(title or "vdo validate: predicted vs measured uncertainty", fontsize=10)
    ax.legend(fontsize=6, ncol=2, loc="upper left")
    ax.grid(True, which="both", alpha=0.3)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_csv(rows: list[dict], path) -> None:
    with open(path, "w", newline="") as fh:
        fh.write(f"# {CONVENTION}\n")
        writer = csv.DictWriter(fh, fieldnames=CSV_FIELDS)
        writer.writeheader()
        for r in rows:
            writer.writerow({k: (f"{v:.5g}" if isinstance(v, float) else v) for k, v in r.items()})


def print_table(rows: list[dict]) -> None:
    """One line per ratio: the sigmas, the ratio, its own 95 % interval, the joint interval its
    verdict rests on (`vdo.dic.verdicts.judge`) and the verdict unless "within"."""
    print(f"{'case':<24}{'axis':>5}{'pred um':>10}{'sqrt2*pred':>12}{'meas um':>10}{'ratio':>8}"
          f"{'95% CI':>15}{'joint CI':>15}{'bias um':>10}{'n':>6}")
    for r in rows:
        flag = {"within": "", "outside": "  OUTSIDE",
                "inconclusive": f"  INCONCLUSIVE ({seeds_needed([r])})"}[r["verdict"]]
        joint = f"{about(r['ratio_joint_low'])}-{about(r['ratio_joint_high'])}"
        print(f"{r['case']:<24}{r['axis']:>5}{r['sigma_predicted_um']:>10.4f}"
              f"{r['sigma_expected_um']:>12.4f}{r['sigma_measured_um']:>10.4f}{r['ratio']:>8.3f}"
              f"{r['ratio_ci95_low']:>8.3f}-{r['ratio_ci95_high']:.3f}{joint:>15}"
              f"{r['bias_um']:>10.4f}{r['n_seeds']:>6}{flag}")


def about(n: float) -> str:
    """An interval's bound as the console shows it: 3 significant digits, a whole number from
    1000 on (1220 rather than 1.22e+03)."""
    return f"{n:.3g}" if n < 1000 else f"{n:.0f}"


def round_up(n: int, digits: int = 2) -> int:
    """`n` rounded up to `digits` significant digits: 47747 -> 48000, 16 -> 16."""
    step = 10 ** max(len(str(n)) - digits, 0)
    return -(-n // step) * step


def seeds_needed(rows: list[dict]) -> str:
    """The seeds that would decide these inconclusive rows at their measured ratios (their
    `seeds_to_decide`, None: never, a ratio on a band edge), as words, rounded up to 2
    significant digits (the ratio they rest on is itself uncertain)."""
    counts = sorted(r["seeds_to_decide"] for r in rows if r["seeds_to_decide"] is not None)
    if not counts:
        return "no seed count decides a ratio on a band edge"
    low, high = (str(round_up(c)) for c in (counts[0], counts[-1]))
    span = low if low == high else f"{low}-{high}"
    return f"~{span} seeds would decide {'it' if len(rows) == 1 else 'them'}"


def verdict_line(summary: dict) -> str:
    """The console's verdict on a run (summary.json's): the counts of ratios outside, inconclusive
    and within the band at the joint confidence; with inconclusive ones, the seeds that would
    decide them at their ratios and those that show a ratio of 1 within (`seeds_to_decide`); the
    noise-free check."""
    n, rows = summary["verdicts"], summary["rows"]
    open_rows = [r for r in rows if r["verdict"] == "inconclusive"]
    hint = (f" ({seeds_needed(open_rows)}; --seeds {seeds_to_decide(1.0, ratios=len(rows))} shows "
            "a ratio of 1 within)") if open_rows else ""
    return (f"ratios against [{BAND[0]:g}, {BAND[1]:g}] at {CONFIDENCE:.0%} joint confidence: "
            f"{n['outside']} OUTSIDE, {n['inconclusive']} INCONCLUSIVE{hint}, {n['within']} within; "
            f"noise-free check {'passed' if summary['noise_free_passed'] else 'FAILED'}")
