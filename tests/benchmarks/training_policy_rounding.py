"""How far rsl_rl's bfloat16 update moves a trained actor's policy by rounding alone, and what the
adaptive learning rate of the runs did.

``python -m tests.benchmarks.training_policy_rounding RUN ... --out reports/<name>`` loads each run's
``checkpoint.pt`` (where kept) and ``config.json`` and recomputes the actor's policy mean on ``--samples``
observations as the PPO update does under ``algorithm.use_mixed_precision`` (``torch.autocast``,
bfloat16, on this CPU: the same bfloat16 rounding of the layers' inputs and outputs as on a GPU),
against the float32 mean the rollout recorded. For each action std σ it reports, from the rounding
δ alone (no weight changed):

* the mean KL divergence Σ δ²/(2σ²) of the update's Gaussian from the rollout's, against rsl_rl's
  adaptive schedule (``desired_kl``: the learning rate falls by 1.5 when the KL exceeds twice it and
  rises only when it is under half of it; rsl_rl 5.5 ``PPO.update``);
* the rms of the log-ratio log π_update(a) − log π_rollout(a) for actions a drawn from the rollout's
  Gaussian, and the share of ratios outside PPO's clip range [1 − ε, 1 + ε] (``clip_param``);

for rsl_rl's ``MLPModel`` (the whole actor in bfloat16) and for sim_twin.training.models'
``Float32MLPModel`` (the actor kept in float32; zero by construction, measured all the same).
Observations are drawn per dimension from the checkpoint's own observation normaliser (its running
mean and std of the training observations), so the actor sees inputs of the training's scale; their
correlations are not kept.

Where a run keeps its TensorBoard events (``tb.tar.gz``) the report adds the learning rate and the
value loss rsl_rl logged (``Loss/learning_rate``, ``Loss/value``) and the curve's mean impact error
and action std at ``--iterations``. Writes ``<name>.json``, ``<name>.md`` and ``<name>.png``.
"""

from __future__ import annotations

import argparse
import json
import platform
import tarfile
import tempfile
from datetime import UTC, datetime
from pathlib import Path

SIGMAS = (0.6, 0.2, 0.1, 0.05)
"""Action stds [-] of the table: the recipes' initial std, two on the schedule and the std floor."""


def rounding(actor, n: int, sigmas=SIGMAS, clip: float = 0.2, seed: int = 0) -> dict:
    """Rounding of ``actor``'s policy mean under bfloat16 autocast, on ``n`` observations drawn from
    its normaliser. Returns {delta_rms: rms of δ [action units], mean_abs: median |mean|, per_sigma:
    [{sigma, kl_mean, log_ratio_rms, clipped_share}]}."""
    import torch
    from tensordict import TensorDict

    g = torch.Generator().manual_seed(seed)
    norm = actor.obs_normalizer
    x = norm.mean + norm.std * torch.randn(n, norm.mean.shape[0], generator=g)
    obs = TensorDict({"policy": x}, batch_size=[n])
    with torch.no_grad():
        mu = actor(obs).float()
        with torch.autocast("cpu", dtype=torch.bfloat16):
            mu_b = actor(obs).float()
    d = mu_b - mu
    out = {"delta_rms": float(d.pow(2).mean().sqrt()), "mean_abs": float(mu.abs().median()), "per_sigma": []}
    for s in sigmas:
        a = mu + s * torch.randn(mu.shape, generator=g)
        log_ratio = (((a - mu) ** 2 - (a - mu_b) ** 2) / (2 * s * s)).sum(1)
        out["per_sigma"].append({
            "sigma": s, "kl_mean": float((d**2 / (2 * s * s)).sum(1).mean()),
            "log_ratio_rms": float(log_ratio.pow(2).mean().sqrt()),
            "clipped_share": float(((log_ratio.exp() - 1).abs() > clip).float().mean())})
    return out


def tb_scalars(run: Path, tags: tuple[str, ...]) -> dict[str, dict[int, float]]:
    """{tag: {step: value}} from ``run/tb.tar.gz`` (every event file in it), {} without one."""
    tar = run / "tb.tar.gz"
    if not tar.exists():
        return {}
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out: dict[str, dict[int, float]] = {t: {} for t in tags}
    with tempfile.TemporaryDirectory() as tmp:
        with tarfile.open(tar) as t:
            t.extractall(tmp, filter="data")
        for f in sorted(Path(tmp).rglob("events.out.tfevents.*")):
            ea = EventAccumulator(str(f), size_guidance={"scalars": 0})
            ea.Reload()
            for tag in tags:
                if tag in ea.Tags()["scalars"]:
                    out[tag].update({e.step: e.value for e in ea.Scalars(tag)})
    return out


def run_course(run: Path, iterations: list[int]) -> list[dict]:
    """Per iteration in ``iterations`` (where the run reached it): learning rate and value loss (from
    TensorBoard, where kept), mean impact error [m] and action std from ``curve.csv``."""
    from sim_twin.training.curve import TrainingCurve

    tb = tb_scalars(run, ("Loss/learning_rate", "Loss/value"))
    curve = {int(r["iteration"]): r for r in TrainingCurve.load_or_new(run / "curve.csv").rows}
    rows = []
    for it in iterations:
        if it not in curve:
            continue
        lr, vl = tb.get("Loss/learning_rate", {}).get(it - 1), tb.get("Loss/value", {}).get(it - 1)
        rows.append({"iteration": it, "learning_rate": lr, "value_loss": vl,
                     "impact_err_m": curve[it].get("impact_err_m"), "action_std": curve[it].get("action_std")})
    return rows


def write_report(report: dict, out: Path) -> None:
    """``out``.json, .md and .png (KL from rounding against σ per run and model; learning rate over
    iterations of the runs with TensorBoard events)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(report, indent=1) + "\n")
    lines = [f"# {report['title']}", "",
             f"Date {report['date']}, commit `{report['commit']}`, host {report['host']}. Command: `{report['command']}`.",
             "", report["method"], "",
             "The rounding columns are what a bfloat16 update computes for each run's final actor, whichever update the run "
             "itself used (its recipe's column).", "",
             "| run | the run's update | actor in a bfloat16 update | σ | KL from rounding (mean) | desired_kl | log-ratio rms | ratios outside the clip range |",
             "|---|---|---|---|---|---|---|---|"]
    for r in report["runs"]:
        for model, m in r["models"].items():
            for s in m["per_sigma"]:
                lines.append(f"| `{r['run']}` | {r['update']} | {model} | {s['sigma']} | {s['kl_mean']:.4f} | {r['desired_kl']} "
                             f"| {s['log_ratio_rms']:.3f} | {100 * s['clipped_share']:.1f} % |")
    lines += ["", "Rounding of the policy mean (whole actor in bfloat16): " + "; ".join(
        f"`{r['run']}` δ rms {r['models']['MLPModel']['delta_rms']:.4f} at median |mean| {r['models']['MLPModel']['mean_abs']:.2f}"
        for r in report["runs"] if r["models"]) + ".", "",
        "The runs' course (learning rate and value loss from rsl_rl's TensorBoard events, `tb.tar.gz`; impact error and "
        "action std from `curve.csv`):", "",
        "| run | the run's update | iteration | learning rate | value loss | mean impact error [m] | action std |", "|---|---|---|---|---|---|---|"]
    for r in report["runs"]:
        for c in r["course"]:
            if c["learning_rate"] is None:
                continue
            lines.append(f"| `{r['run']}` | {r['update']} | {c['iteration']} | {c['learning_rate']:.2e} | {c['value_loss']:.2f} "
                         f"| {c['impact_err_m']:.3f} | {c['action_std']:.3f} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    for r in report["runs"]:
        if r["models"]:
            m = r["models"]["MLPModel"]
            ax1.plot([s["sigma"] for s in m["per_sigma"]], [s["kl_mean"] for s in m["per_sigma"]], "o-", label=f"{r['run']} (bf16 actor)")
        lr = [(c["iteration"], c["learning_rate"]) for c in r["course"] if c["learning_rate"] is not None]
        if lr:
            ax2.plot(*zip(*lr), "o-", label=f"{r['run']} ({r['update']})")
    ax1.axhline(report["runs"][0]["desired_kl"], color="k", ls="--", lw=1, label="desired_kl")
    ax1.axhline(2 * report["runs"][0]["desired_kl"], color="r", ls=":", lw=1, label="2 × desired_kl (learning rate cut)")
    ax1.set(xscale="log", yscale="log", xlabel="action std σ", ylabel="mean KL from rounding alone",
            title="bfloat16 update: KL with no weight changed")
    ax1.set_xticks(report["sigmas"], [str(x) for x in report["sigmas"]])
    ax1.minorticks_off()
    ax2.set(yscale="log", xlabel="iteration", ylabel="learning rate", title="rsl_rl adaptive learning rate")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"), dpi=110)
    plt.close(fig)


def main() -> None:
    """CLI: ``RUN ... --out reports/<name>`` (see the module docstring)."""
    import torch
    from rsl_rl.models import MLPModel

    from sim_twin.training.export import load_actor
    from sim_twin.provenance import head_commit
    from sim_twin.training.models import Float32MLPModel

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", type=Path, nargs="+", help="run directories with checkpoint.pt and config.json")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--samples", type=int, default=65536)
    p.add_argument("--iterations", default="100,200,300,400,500,600,800,1000,1200",
                   help="iterations of the runs' course table")
    a = p.parse_args()
    torch.manual_seed(0)
    iterations = [int(i) for i in a.iterations.split(",")]
    runs = []
    for run in a.runs:
        cfg = json.loads((run / "config.json").read_text())
        models = {}  # a run that kept no checkpoint (only its exported policy) gives its course alone
        for cls in (MLPModel, Float32MLPModel) if (run / "checkpoint.pt").exists() else ():
            actor, _ = load_actor(run / "checkpoint.pt", cfg, cls)
            models[cls.__name__] = rounding(actor, a.samples, clip=cfg["runner"]["algorithm"].get("clip_param", 0.2))
        alg = cfg["runner"]["algorithm"]
        update = ("bf16" if alg.get("use_mixed_precision") else "fp32") + f", γ {alg['gamma']}"
        runs.append({"run": run.name, "update": update, "desired_kl": alg.get("desired_kl"),
                     "models": models, "course": run_course(run, iterations)})
    report = {
        "title": "bfloat16 PPO update: the policy's rounding against the adaptive learning rate (2D actors)",
        "date": datetime.now(UTC).isoformat(timespec="seconds"), "commit": (head_commit() or ("unknown",))[0], "host": platform.node(),
        "command": "python -m tests.benchmarks.training_policy_rounding " + " ".join(str(r) for r in a.runs) + f" --out {a.out}",
        "method": __doc__.split("\n\n")[1].replace("\n", " "), "sigmas": list(SIGMAS), "samples": a.samples, "runs": runs,
    }
    write_report(report, a.out)
    print(a.out.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
