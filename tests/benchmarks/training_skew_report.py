"""Where does a 2D policy's far-target bias sit between the nominal machine and its training
distribution? Several ``tests.benchmarks.training_twin_bias --training-dist`` outputs side by side.

    python -m tests.benchmarks.training_skew_report LABEL=BIAS.json [LABEL=BIAS.json ...] \
        --out reports/training_skew_2d [--title TITLE]

Each BIAS.json is a ``training_twin_bias --json`` output of one policy with ``--training-dist`` (and
its default env-delay rollout ``env``). Per policy and target the report gives, in the MJX training
environment and from the same start poses and targets (the site matrix's seed-0 poses):

* the mean signed downrange error on the **nominal machine** (``env``: the config narrowed to the
  nominal machine, the environment's own release delays) and on the **training distribution**
  (``training-dist``: the config's own randomisation), each with its standard error;
* the **skew**: nominal minus training distribution, paired throw by throw over the throws that landed
  in both, with the standard error of the paired mean. A skew of zero means the nominal machine lands
  where the policy's training distribution lands on average; a positive skew is the nominal machine
  throwing long relative to the policy's own training (docs/training.md, "Four more seeds, and the
  far-target overshoot").

Writes ``<out>.json`` (per policy: the benchmark's arguments and the rows), ``<out>.md`` and
``<out>.png`` (the skew against the target, one line per policy, ± 1 standard error). Raises
SystemExit with a message for an input without the ``env`` or ``training-dist`` rollout.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from tests.benchmarks.training_twin_bias import DELAY_CHOICES, mean_se, paired, side_summary


def _relative(path: str) -> str:
    """``path`` relative to the working directory where it lies under it (the benchmark records what it was given)."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd()))
    except ValueError:
        return path


def skew_rows(bench: dict) -> list[dict]:
    """Per target of one ``training_twin_bias`` output: nominal-machine and training-distribution bias
    [m] with standard errors, the paired skew (nominal - training distribution) [m], and where the
    training distribution draws a wind, the mean downrange shift of its landings over the config's
    winds, each throw's own release averaged over every wind (``wind_mean_downrange_m``,
    training_twin_bias.mean_wind_shift; ``training_wind_m`` with its standard error over the throws;
    None without wind): what the air takes from the training distribution's throws on average, which
    the nominal machine, in still air, does not lose.

    Raises:
        ValueError: the output has no ``env`` or no ``training-dist`` rollout.
    """
    env = bench.get("env", {})
    for name in ("env", "training-dist"):
        if name not in env:
            raise ValueError(f"no '{name}' rollout (run training_twin_bias with --training-dist and env in --env-delay)")
    rows = []
    for target in env["env"]:
        nom, dist = env["env"][target], env["training-dist"][target]
        n, d = side_summary(nom), side_summary(dist)
        sk, ss, pairs = paired(nom, dist)["downrange_m"]  # by start-pose seed, over throws landed in both
        windy = [r["wind_mean_downrange_m"] for r in dist if r.get("landed") and "wind_mean_downrange_m" in r]
        wind, wind_se, _ = mean_se(windy) if windy else (None, None, 0)
        rows.append({"target_m": float(target), "throws": len(nom), "pairs": pairs,
                     "nominal_bias_m": n["bias_m"], "nominal_se_m": n["se_m"],
                     "training_dist_bias_m": d["bias_m"], "training_dist_se_m": d["se_m"], "skew_m": sk, "skew_se_m": ss,
                     "training_wind_m": wind, "training_wind_se_m": wind_se})
    return rows


ROLLOUTS_OF_THE_CHAIN = (*DELAY_CHOICES, "training-dist")
"""training_twin_bias's rollouts that are not a parameter setting (``--env-set``)."""


def setting_rows(bench: dict) -> list[dict]:
    """Per ``--env-set`` rollout of one ``training_twin_bias`` output (the nominal machine with some
    per-episode parameters set, e.g. to their training distribution's mean) and target: its bias [m]
    with standard error, and its change from the nominal machine, paired throw by throw (setting -
    nominal). [] for an output without such rollouts."""
    env = bench.get("env", {})
    rows = []
    for name, per in env.items():
        if name in ROLLOUTS_OF_THE_CHAIN:
            continue
        for target, thrown in per.items():
            b = side_summary(thrown)
            ch, ch_se, pairs = paired(thrown, env["env"][target])["downrange_m"]
            rows.append({"setting": name, "target_m": float(target), "bias_m": b["bias_m"], "se_m": b["se_m"],
                         "change_m": ch, "change_se_m": ch_se, "pairs": pairs})
    return rows


def render(policies: list[dict], title: str) -> list[str]:
    """The report's Markdown lines: one table of every policy and target."""
    lines = [f"# {title}", "", "Positive = long; ± one standard error of the mean; skew = nominal machine - training "
             "distribution, paired throw by throw (same start pose and target); the winds' shift: each landed throw's "
             "release averaged over the recipe's winds (training_twin_bias.mean_wind_shift), then over the throws.", "",
             "| policy | training config | target [m] | nominal machine [m] | training distribution [m] | skew [m] "
             "| of the training distribution, its winds' shift [m] |",
             "|---|---|---|---|---|---|---|"]
    for p in policies:
        for r in p["rows"]:
            wind = "-" if r.get("training_wind_m") is None else f"{r['training_wind_m']:+.3f} ± {r['training_wind_se_m']:.3f}"
            lines.append(f"| {p['label']} | `{p['config']}` | {r['target_m']:g} | {r['nominal_bias_m']:+.3f} ± {r['nominal_se_m']:.3f} "
                         f"| {r['training_dist_bias_m']:+.3f} ± {r['training_dist_se_m']:.3f} | **{r['skew_m']:+.3f}** ± {r['skew_se_m']:.3f} "
                         f"| {wind} |")
    for p in policies:
        if not p.get("settings"):
            continue
        targets = sorted({r["target_m"] for r in p["settings"]})
        lines += ["", f"**{p['label']}: the nominal machine with parameters set** (EnvState fields after the reset; "
                  "bias [m], and in brackets its change from the nominal machine, paired throw by throw)", "",
                  "| setting | " + " | ".join(f"{t:g} m" for t in targets) + " |", "|---|" + "---|" * len(targets)]
        for name in dict.fromkeys(r["setting"] for r in p["settings"]):
            cells = {r["target_m"]: r for r in p["settings"] if r["setting"] == name}
            lines.append(f"| `{name}` | " + " | ".join(
                f"{cells[t]['bias_m']:+.3f} ± {cells[t]['se_m']:.3f} ({cells[t]['change_m']:+.3f})" for t in targets) + " |")
    return lines + [""]


def plot(policies: list[dict], path: Path) -> None:
    """The skew against the target distance, one line per policy, error bars ± 1 SE."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    for k, p in enumerate(policies):
        xs = [r["target_m"] + 0.04 * (k - len(policies) / 2) for r in p["rows"]]
        ax.errorbar(xs, [r["skew_m"] for r in p["rows"]], yerr=[r["skew_se_m"] for r in p["rows"]], marker="o",
                    capsize=3, label=p["label"])
    ax.axhline(0.0, color="0.6", lw=0.8)
    ax.set_xlabel("target distance [m]")
    ax.set_ylabel("nominal - training distribution [m]")
    ax.set_title("2D far-target bias: nominal machine - training distribution (MJX environment)", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("inputs", nargs="+", metavar="LABEL=BIAS.json", help="a label and a training_twin_bias --json output")
    ap.add_argument("--out", type=Path, required=True, help="output stem (.json, .md, .png)")
    ap.add_argument("--title", default="Far-target bias of 2D policies: nominal machine against the training distribution")
    args = ap.parse_args(argv)
    policies = []
    for spec in args.inputs:
        label, sep, path = spec.partition("=")
        if not sep or not label:
            raise SystemExit(f"training_skew_report: expected LABEL=BIAS.json, got {spec!r}")
        bench = json.loads(Path(path).read_text())
        try:
            rows = skew_rows(bench)
        except ValueError as e:
            raise SystemExit(f"training_skew_report: {path}: {e}") from None
        policies.append({"label": label, "policy": _relative(bench["args"]["policy"]), "config": _relative(bench["args"]["config"]),
                         "benchmark_args": bench["args"], "rows": rows, "settings": setting_rows(bench)})
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps({"title": args.title, "policies": policies}, indent=2) + "\n")
    args.out.with_suffix(".md").write_text("\n".join(render(policies, args.title)))
    plot(policies, args.out.with_suffix(".png"))
    print("\n".join(render(policies, args.title)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
