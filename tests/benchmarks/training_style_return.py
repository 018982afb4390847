"""Which far-target style scores more of the training's own objective: each 2D run's undiscounted
return, term by term, in the MJX training environment.

``python -m tests.benchmarks.training_style_return RUN ... --out reports/<name>`` loads each run's
``checkpoint.pt`` and ``config.json`` (a directory or ``REV:PATH``, as the style probe reads them),
exports the actor (sim_twin.training.export) and plays ``--envs`` episodes with the run's own
randomisation and target range (the training distribution; forced release off, as in the site
matrix), the same PRNG keys for every run. Per run and target band it records the mean sum over the
episode of every reward term (``info["reward_terms"]``, the scaled terms the reward adds up,
sim_twin.training.rewards), the mean return (their sum: the return with γ 1.0, the candidate
recipe's discount), the landing error and the episode length; and from the run's gate matrices how
many throws ended without a release, by target. The run's style comes from its gate
(tests/benchmarks/training_throw_style.py). Writes ``<name>.json``, ``<name>.md`` and ``<name>.png``
(mean return by target band and run, long-style runs blue, short red).

A short-style run that scores as much as the long-style runs on this objective would mean the
reward does not prefer the long style; one that scores less is a worse optimum PPO did not leave.
Runs on the CPU (JAX) in a few minutes per run.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from tests.benchmarks.training_style_probe import play, probe_actor, without_forced_release
from tests.benchmarks.training_throw_style import RunSource, run_style

RETURN_KEY = 11
"""PRNG key of the episodes (start poses, targets, randomisation): the same for every run."""
BANDS_M = ((5.0, 7.5), (7.5, 9.0), (9.0, 10.7))
"""Target-distance bands [m] the returns are split by (the site matrix's targets are 7.5-10 m)."""


def episode_returns(onnx_path: Path, env_cfg: dict, envs: int, key: int = RETURN_KEY, forced_release: bool = False) -> dict:
    """Play one episode in each of ``envs`` MJX training environments with the exported actor.

    Args:
        onnx_path: the actor, input (N, observation_size) float32.
        env_cfg: the ``env`` mapping of a training config (its randomisation and target range as given).
        envs: number of episodes.
        key: PRNG key of the resets.
        forced_release: keep the config's forced release (paper Sec. III-D: the gripper opened at
            random when it hangs slowly near the target), as in training; off (the default) as in
            the site matrix and on the machine.

    Returns:
        {"target_m": (envs,) target distance [m], "terms": {term: (envs,) sum over the episode of the
        scaled term}, "landed": (envs,) bool, "failed": (envs,) bool, "impact_err_m": (envs,) landing
        error [m] (nan without a landing), "steps": (envs,) control steps played}.
    """
    cfg = env_cfg if forced_release else without_forced_release(env_cfg)
    target_m = np.zeros(envs)
    sums: dict[str, np.ndarray] = {}
    landed, failed = np.zeros(envs, bool), np.zeros(envs, bool)
    err, steps = np.full(envs, np.nan), np.zeros(envs, int)
    for k, before, _, info, live in play(onnx_path, cfg, envs, key):
        if k == 0:
            target_m = np.linalg.norm(np.asarray(before.target)[:, :2], axis=1)
        for name, v in info["reward_terms"].items():
            sums.setdefault(name, np.zeros(envs))[live] += np.asarray(v)[live]
        steps[live] += 1
        new_land = np.asarray(info["landed"]) & live
        landed |= new_land
        err[new_land] = np.asarray(info["impact_err_m"])[new_land]
        failed |= np.asarray(info["failed"]) & live
    return {"target_m": target_m, "terms": sums, "landed": landed, "failed": failed, "impact_err_m": err, "steps": steps}


def summarise(ep: dict) -> list[dict]:
    """Per target band of :data:`BANDS_M` (and ``all``): episodes, mean return with its standard
    error, the mean of every term, landed and failed fractions, the landing error's mean and
    standard deviation [m] and the mean episode length [control steps]."""
    ret = sum(ep["terms"].values())
    out = []
    for lo, hi in (*BANDS_M, (0.0, np.inf)):
        m = (ep["target_m"] >= lo) & (ep["target_m"] < hi)
        if not m.any():
            continue
        e = ep["impact_err_m"][m & ep["landed"]]
        out.append({"band": "all" if hi == np.inf else f"{lo:g}-{hi:g} m", "episodes": int(m.sum()),
                    "return": float(ret[m].mean()), "return_sem": float(ret[m].std(ddof=1) / np.sqrt(m.sum())) if m.sum() > 1 else 0.0,
                    "terms": {k: float(v[m].mean()) for k, v in ep["terms"].items()},
                    "landed": float(ep["landed"][m].mean()), "failed": float(ep["failed"][m].mean()),
                    "impact_err_m": float(e.mean()) if e.size else float("nan"),
                    "impact_err_sd_m": float(e.std()) if e.size else float("nan"),
                    "steps": float(ep["steps"][m].mean())})
    return out


GATE_FROM_ITERATION = 200
"""The gate's matrices from this iteration on count in :func:`gate_no_release` (the style is set by then)."""


def gate_no_release(src: RunSource, from_iteration: int = GATE_FROM_ITERATION) -> dict[str, list[int]]:
    """Throws of the run's gate matrices (every profile and seed, iterations from ``from_iteration``)
    that ended without a release ("no release within 10 s"), by target: {"7.5": [failed, throws]};
    {} for a run that kept no gate matrices."""
    import re

    out: dict[str, list[int]] = {}
    for name in src.list("matrices"):
        m = re.fullmatch(r"site_matrix_2d_it(\d+)(?:_seed\d+)?\.json", name)
        if not m or int(m.group(1)) < from_iteration:
            continue
        for prof in json.loads(src.read(f"matrices/{name}"))["profiles"]:
            for t in prof["targets"]:
                c = out.setdefault(f"{t['target_m']:g}", [0, 0])
                c[0] += int(t.get("failures", {}).get("no release within 10 s", 0))
                c[1] += int(t["throws"])
    return dict(sorted(out.items(), key=lambda kv: float(kv[0])))


def gate_no_release_table(rows: list[dict]) -> list[str]:
    """Markdown lines: each row's :func:`gate_no_release` counts by target, and over all targets
    (rows with ``run``, ``gamma`` and ``gate_no_release``; runs without gate matrices left out)."""
    targets = sorted({t for r in rows for t in r["gate_no_release"]}, key=float)
    md = ["", f"Throws of each run's gate matrices (iteration {GATE_FROM_ITERATION} on, every profile and seed, the CPU twin "
          "without forced release, the actor's mean) that ended without a release, by target [m]:", "",
          "| run | γ | " + " | ".join(targets) + " | all |", "|" + "---|" * (len(targets) + 3)]
    for r in rows:
        if not r["gate_no_release"]:
            continue
        cells = [r["gate_no_release"].get(t, [0, 0]) for t in targets]
        failed, throws = sum(c[0] for c in cells), sum(c[1] for c in cells)
        md.append(f"| {r['run']} | {r['gamma']} | " + " | ".join(f"{c[0]} / {c[1]}" for c in cells)
                  + f" | {failed} / {throws} ({failed / max(throws, 1):.2%}) |")
    return md


def run_row(src: RunSource, envs: int, workdir: Path) -> dict:
    """One run: its style by the gate, its checkpoint's iteration and :func:`summarise` of its episodes.

    Raises:
        FileNotFoundError: the run lacks config.json or checkpoint.pt.
        ValueError: a 3D run.
    """
    cfg = json.loads(src.read("config.json"))
    onnx_path, iteration = probe_actor(src, cfg, workdir)
    try:
        style = run_style(src)["style"]
    except (FileNotFoundError, ValueError, KeyError, StopIteration):
        style = None
    ep = episode_returns(onnx_path, cfg["env"], envs)
    return {"run": src.name, "source": src.spec, "training_seed": cfg.get("training", {}).get("seed"),
            "gamma": cfg["runner"]["algorithm"].get("gamma"), "iteration": iteration, "style": style, "envs": envs,
            "bands": summarise(ep), "gate_no_release": gate_no_release(src)}


def plot(rows: list[dict], path: Path) -> None:
    """Mean return (± standard error) by target band, one marker per run (long blue, short red)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bands = [b["band"] for b in rows[0]["bands"]]
    fig, ax = plt.subplots(figsize=(7, 3.8))
    for j, r in enumerate(rows):
        x = np.arange(len(bands)) + (j - (len(rows) - 1) / 2) * 0.08
        y = [b["return"] for b in r["bands"]]
        e = [b["return_sem"] for b in r["bands"]]
        ax.errorbar(x, y, yerr=e, fmt="o", color={"long": "tab:blue", "short": "tab:red"}.get(r["style"], "grey"), ms=5, capsize=2)
        ax.annotate(r["run"].replace("throw2d-scratch-", "-"), (x[-1], y[-1]), textcoords="offset points", xytext=(4, 0), fontsize=7)
    ax.set_xticks(range(len(bands)), [f"targets {b}" for b in bands])
    ax.set_ylabel("mean undiscounted return")
    ax.set_title("2D runs: return on the training objective by target band (long blue, short red)", fontsize=9)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def runs_parser(doc: str, envs_help: str) -> argparse.ArgumentParser:
    """The command line of a tool that plays runs in the MJX training environment: RUN ... (directories
    or REV:PATH), ``--out`` (report stem) and ``--envs`` (episodes, default 512)."""
    p = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="run directories or REV:PATH")
    p.add_argument("--out", type=Path, required=True, help="report stem (writes .json, .md and .png)")
    p.add_argument("--envs", type=int, default=512, help=envs_help)
    return p


def rows_of(specs: list[str], row, say) -> list[dict]:
    """``row(RunSource(spec), workdir)`` for every run spec in order, with a scratch directory for the
    exported actors; ``say(row)`` gives a progress line after each."""
    with tempfile.TemporaryDirectory() as tmp:
        rows = []
        for spec in specs:
            rows.append(row(RunSource(spec), Path(tmp)))
            print(say(rows[-1]), flush=True)
    return rows


def main() -> None:
    a = runs_parser(__doc__, "episodes per run").parse_args()

    def say(r: dict) -> str:
        b = r["bands"][-1]
        return f"{r['run']}: {r['style']}, return {b['return']:.2f} ± {b['return_sem']:.2f}"

    rows = rows_of(a.runs, lambda src, tmp: run_row(src, a.envs, tmp), say)
    out = {"date": datetime.now(UTC).isoformat(timespec="seconds"), "envs": a.envs, "key": RETURN_KEY, "rows": rows}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.with_suffix(".json").write_text(json.dumps(out, indent=1) + "\n")
    terms = list(rows[0]["bands"][0]["terms"])
    md = ["# 2D runs: undiscounted return on the training objective, by far-target style", "",
          f"{a.envs} episodes per run in the MJX training environment with the run's own randomisation and targets "
          f"(forced release off), PRNG key {RETURN_KEY} for every run; the scaled reward terms summed over each episode "
          "(`info[\"reward_terms\"]`), their sum the return with γ 1.0. Style from the run's gate.", "",
          "| run | seed | γ | iteration | style | targets | episodes | return ± s.e. | " + " | ".join(terms)
          + " | landed | impact error mean / sd [m] | steps |",
          "|" + "---|" * (12 + len(terms))]
    for r in rows:
        for b in r["bands"]:
            md.append(f"| {r['run']} | {r['training_seed']} | {r['gamma']} | {r['iteration']} | {r['style']} | {b['band']} | "
                      f"{b['episodes']} | {b['return']:.2f} ± {b['return_sem']:.2f} | "
                      + " | ".join(f"{b['terms'][t]:.3f}" for t in terms)
                      + f" | {b['landed']:.1%} | {b['impact_err_m']:.3f} / {b['impact_err_sd_m']:.3f} | {b['steps']:.1f} |")
    md += gate_no_release_table(rows)
    a.out.with_suffix(".md").write_text("\n".join(md) + "\n")
    plot(rows, a.out.with_suffix(".png"))


if __name__ == "__main__":
    main()
