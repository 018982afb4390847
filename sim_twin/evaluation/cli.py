"""``slinger evaluate``: the command line of the evaluation protocol (sim_twin.evaluation.evaluate) and the
site matrix (sim_twin.evaluation.matrix), the paper's figure and the Markdown table of a report.

``slinger evaluate --policy policies/throw2d.onnx --targets 7.5:10:0.5 --throws 200`` writes a
JSON report and the paper's figure (mean impact with 1 sigma bars against the target);
``--matrix`` runs the site matrix instead. ``--engine drake`` throws at the machine in Drake
(sim_twin.twin.drake_machine) instead of the MuJoCo twin: the report names the engine, and a nominal
Drake evaluation is paired throw by throw with the MuJoCo site matrix's nominal column
(sim_twin.evaluation.drake_evaluate): both engines in one figure, the nominal column's bars in each.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path

import numpy as np

from runtime.entrypoint import module_main
from sim_twin.evaluation.evaluate import evaluate
from sim_twin.twin.engines import ENGINES

log = logging.getLogger(__name__)


def plot_reports(reports: list[dict], out: Path) -> None:
    """The paper's figure: mean impact distance with 1 sigma bars against the target distance,
    one panel per report (2D and 3D side by side)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(reports), figsize=(5.2 * len(reports), 4.4), squeeze=False)
    for ax, rep in zip(axes[0], reports):
        rows = [t for t in rep["targets"] if t["landed"]]
        d = np.array([t["target_m"] for t in rows])
        ax.plot([d.min() - 0.5, d.max() + 0.5], [d.min() - 0.5, d.max() + 0.5], "k--", lw=0.8, label="target")
        ax.errorbar(d, [t["mean_impact_m"] for t in rows], yerr=[t["sigma_downrange_m"] for t in rows], fmt="o", capsize=4, label="mean impact ± 1σ downrange")
        ax.errorbar(d + 0.08, [t["target_m"] + t["mean_crossrange_m"] for t in rows], yerr=[t["sigma_crossrange_m"] for t in rows],
                    fmt="s", ms=3, capsize=3, alpha=0.7, label="target + mean crossrange ± 1σ")
        ax.set_xlabel("target distance [m]")
        ax.set_ylabel("impact distance [m]")
        name = rep.get("policy_version", rep["mode"])
        ax.set_title(f"{rep['mode'].upper()} policy {name}, {rep['throws_per_target']} throws/target ({rep['profile']}, {rep.get('engine', 'mujoco')})",
                     fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def markdown_table(report: dict) -> str:
    """The per-target statistics of a report as a Markdown table (for docs and reports)."""
    head = (f"**{report['mode'].upper()} `{report.get('policy_version', report['policy'])}`**, "
            f"{report['throws_per_target']} throws per target, {report['profile']} profile\n\n"
            "| target [m] | success | mean impact [m] | bias [m] | σ downrange [m] | mean crossrange [m] | σ crossrange [m] | duration [s] |\n"
            "|---|---|---|---|---|---|---|---|\n")
    rows = []
    for t in report["targets"]:
        def f(key, fmt="{:+.3f}", t=t):
            return "n/a" if t[key] is None else fmt.format(t[key])
        rows.append(f"| {t['target_m']:.1f} | {100 * t['success_rate']:.1f} % | {f('mean_impact_m', '{:.3f}')} | {f('bias_m')} | "
                    f"{f('sigma_downrange_m', '{:.3f}')} | {f('mean_crossrange_m')} | {f('sigma_crossrange_m', '{:.3f}')} | "
                    f"{f('mean_duration_s', '{:.2f}')} |")
    return head + "\n".join(rows) + "\n"


def parse_targets(spec: str) -> list[float]:
    """"8.5" or "7.5,8" or "7.5:10:0.5" (start:stop:step, stop included) -> distances in m.

    Raises:
        ValueError: malformed spec or a non-positive step.
    """
    if ":" in spec:
        a, b, s = (float(x) for x in spec.split(":"))
        if s <= 0:
            raise ValueError("target step must be > 0")
        return [round(a + k * s, 6) for k in range(int(math.floor((b - a) / s + 1e-9)) + 1)]
    return [float(x) for x in spec.split(",")]


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--policy", type=Path, default=Path("policies/throw2d.onnx"))
    parser.add_argument("--targets", default=None, help="2D default 7.5:10:0.5, 3D default 7:9.5:0.5")
    parser.add_argument("--throws", type=int, default=200, help="throws per target")
    parser.add_argument("--profile", type=Path, default=None, help="reality profile JSON (default nominal)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--out", type=Path, default=None, help="JSON report (default reports/eval_<mode>.json)")
    parser.add_argument("--plot", type=Path, default=None, help="PNG figure (default beside the JSON)")
    parser.add_argument("--release-sweep", action="store_true",
                        help="--matrix: first the policy validation's twin sweep over the declared range; the matrix passes only with it")
    parser.add_argument("--matrix", action="store_true",
                        help="run the site matrix (nominal + sim_twin/profiles site profiles, sim_twin.evaluation.matrix) and write "
                             "reports/site_matrix_<mode>.json/.md/.png (or --out); default 100 throws per target")
    parser.add_argument("--engine", choices=ENGINES, default="mujoco",
                        help="physics engine of the simulated machine: mujoco (the twin the policies were trained on) or drake "
                             "(an independent engine; default report reports/eval_<mode>_drake.json)")
    parser.add_argument("--matrix-report", type=Path, default=None,
                        help="--engine drake: the MuJoCo site matrix whose nominal column the evaluation is paired with "
                             "(default reports/site_matrix_<mode>.json)")
    parser.add_argument("--combine", type=Path, nargs="+", default=None,
                        help="only draw the figure of these JSON reports side by side (e.g. 2D and 3D) to --plot")


def run(args: argparse.Namespace) -> int:
    from runtime.policy import PolicyRunner

    if args.combine:
        reports = [json.loads(p.read_text()) for p in args.combine]
        if all("engines" in r for r in reports):  # Drake evaluations paired with MuJoCo: both engines per panel
            from sim_twin.evaluation.drake_evaluate import markdown, plot_engines

            plot_engines([r["engines"] for r in reports], args.plot or Path("reports/eval_engines.png"))
            print("\n".join(markdown(r["engines"]) for r in reports))
            return 0
        plot_reports(reports, args.plot or Path("reports/eval.png"))
        print("\n".join(markdown_table(r) for r in reports))
        return 0

    mode = PolicyRunner.load(args.policy).mode
    targets = parse_targets(args.targets or ("7.5:10:0.5" if mode == "2d" else "7:9.5:0.5"))
    if args.matrix:
        from sim_twin.evaluation import matrix

        throws = 100 if args.throws == 200 else args.throws  # 200 is the single-profile default
        rep = matrix.run_matrix(args.policy, mode, targets, throws, seed=args.seed, workers=args.workers,
                                release_sweep=args.release_sweep)
        out = args.out or Path("reports") / f"site_matrix_{mode}.json"
        matrix.write(rep, out)
        log.info("site matrix %s: all bars met: %s; %s", mode, rep["pass"], out.with_suffix(".md"))
        return 0
    drake = args.engine == "drake"
    report = evaluate(args.policy, mode, targets, args.throws, args.profile, args.seed, args.workers, engine=args.engine, per_throw=drake)
    out = args.out or Path("reports") / (f"eval_{mode}_drake.json" if drake else f"eval_{mode}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    from sim_twin.evaluation.drake_evaluate import compare_engines, markdown, plot_engines

    if drake and args.profile is None:
        try:
            report["engines"] = compare_engines(report, json.loads((args.matrix_report or Path("reports") / f"site_matrix_{mode}.json").read_text()))
        except (OSError, ValueError) as e:  # e.g. other targets than the matrix's: the seeds differ
            log.warning("Drake evaluation not paired with the MuJoCo site matrix: %s", e)
    if "engines" in report:
        plot_engines([report["engines"]], args.plot or out.with_suffix(".png"))
        print(markdown(report["engines"]))
    else:
        plot_reports([report], args.plot or out.with_suffix(".png"))
    out.write_text(json.dumps(report, indent=2) + "\n")
    for t in report["targets"]:
        log.info(
            "target %.2f m: success %.0f%%, bias %s m, sigma down %s m, sigma cross %s m, mean |error| %s m",
            t["target_m"], 100 * t["success_rate"], _fmt(t["bias_m"]), _fmt(t["sigma_downrange_m"]),
            _fmt(t["sigma_crossrange_m"]), _fmt(t["mean_abs_error_m"]),
        )
    log.info("report: %s", out)
    return 0


def _fmt(x) -> str:
    return "n/a" if x is None else f"{x:+.3f}"


def main(argv: list[str] | None = None) -> int:
    return module_main("slinger evaluate", __doc__, build_parser, run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
