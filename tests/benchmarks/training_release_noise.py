"""Does the actor's mean release where the sampled actor of training does? Each 2D run's throws in the
MJX training environment, played with the actor's mean and with PPO's action noise, side by side.

``python -m tests.benchmarks.training_release_noise RUN ... --out reports/<name>`` loads each run's
``checkpoint.pt`` and ``config.json`` (a directory or ``REV:PATH``), exports the actor
(sim_twin.training.export) and plays ``--envs`` episodes twice with the same PRNG key (start poses,
targets, randomisation): once with the actor's mean, as the site matrix, the validation and the
machine play it, and once with Gaussian noise of std ``--action-std`` on every action entry (0.05:
the std floor every 2D run's learned std reaches, as PPO samples actions in training). Training's
forced release is off in both (the candidate recipe's setting; the older recipes' runs trained with
it). The release flag is the action's last entry and opens the gripper above 0.9 (paper Sec. III-D,
runtime.observation.RELEASE_THRESHOLD).

Per run and target band it records the fraction of episodes that released at all, that landed, and,
for the mean's unreleased episodes, the highest flag the mean reached (a flag that hovers just under
0.9 is one the noise lifts over it in training, and the mean never does). Beside them, the throws of
the run's gate matrices that ended without a release (tests/benchmarks/training_style_return.py).
Writes ``<name>.json``, ``<name>.md`` and ``<name>.png`` (unreleased fraction by band, mean against
sampled, per run). Runs on the CPU (JAX) in a few minutes per run.
"""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from runtime.observation import CONTROL_PERIOD_S, RELEASE_THRESHOLD
from tests.benchmarks.training_style_probe import play, probe_actor, without_forced_release
from tests.benchmarks.training_style_return import BANDS_M, RETURN_KEY, gate_no_release, gate_no_release_table, rows_of, runs_parser
from tests.benchmarks.training_throw_style import RunSource, kept_rows

ACTION_STD = 0.05
"""Default noise std: the 2D recipes' std floor (``runner.actor.distribution_cfg.std_range[0]``)."""


def release_episodes(onnx_path: Path, env_cfg: dict, envs: int, action_std: float, key: int = RETURN_KEY) -> dict:
    """Play one episode in each of ``envs`` MJX training environments, forced release off.

    Args:
        onnx_path: the actor, input (N, observation_size) float32, output (N, actions) whose last entry
            is the release flag.
        env_cfg: the ``env`` mapping of a training config (its randomisation and target range as given).
        envs: number of episodes.
        action_std: std of the Gaussian noise added to every action entry (0: the actor's mean).
        key: PRNG key of the resets (and seed of the noise).

    Returns:
        {"target_m": (envs,) target distance [m], "released": (envs,) bool, "landed": (envs,) bool,
        "failed": (envs,) bool, "flag_max": (envs,) highest release flag of the actor's mean before the
        episode released (over the whole episode where it never did), "release_s": (envs,) time of
        the release command [s from the episode's start] (nan without one)}.
    """
    cfg = without_forced_release(env_cfg)
    target_m = np.zeros(envs)
    released, landed, failed = np.zeros(envs, bool), np.zeros(envs, bool), np.zeros(envs, bool)
    flag_max, release_s = np.full(envs, -np.inf), np.full(envs, np.nan)
    for k, before, _, info, live in play(onnx_path, cfg, envs, key, action_std=action_std):
        if k == 0:
            target_m = np.linalg.norm(np.asarray(before.target)[:, :2], axis=1)
        holding = live & ~released
        flag_max[holding] = np.maximum(flag_max[holding], info["action_mean"][holding, -1])
        now = np.asarray(info["released"]) & holding
        release_s[now] = (k + 1) * CONTROL_PERIOD_S
        released |= now
        landed |= np.asarray(info["landed"]) & live
        failed |= np.asarray(info["failed"]) & live
    return {"target_m": target_m, "released": released, "landed": landed, "failed": failed,
            "flag_max": flag_max, "release_s": release_s}


def summarise(ep: dict) -> list[dict]:
    """Per target band of BANDS_M (and ``all``): episodes, released / landed / failed fractions,
    the median release time [s], and over the unreleased episodes the quartiles of the mean's highest
    flag and the fraction within 0.1 of the threshold."""
    out = []
    for lo, hi in (*BANDS_M, (0.0, np.inf)):
        m = (ep["target_m"] >= lo) & (ep["target_m"] < hi)
        if not m.any():
            continue
        un = ep["flag_max"][m & ~ep["released"]]
        rel = ep["release_s"][m & ep["released"]]
        out.append({"band": "all" if hi == np.inf else f"{lo:g}-{hi:g} m", "episodes": int(m.sum()),
                    "released": float(ep["released"][m].mean()), "landed": float(ep["landed"][m].mean()),
                    "failed": float(ep["failed"][m].mean()),
                    "release_s_median": float(np.median(rel)) if rel.size else float("nan"),
                    "unreleased": int(un.size),
                    "unreleased_flag_quartiles": [float(q) for q in np.percentile(un, [25, 50, 75])] if un.size else [],
                    "unreleased_flag_within_0_1": float((un > RELEASE_THRESHOLD - 0.1).mean()) if un.size else float("nan")})
    return out


def run_row(src: RunSource, envs: int, action_std: float, workdir: Path) -> dict:
    """One run: its checkpoint's iteration and :func:`summarise` of its episodes with the mean
    (``mean``) and with the noise (``sampled``).

    Raises:
        FileNotFoundError: the run lacks config.json or checkpoint.pt.
        ValueError: a 3D run.
    """
    cfg = json.loads(src.read("config.json"))
    onnx_path, iteration = probe_actor(src, cfg, workdir)
    return {"run": src.name, "source": src.spec, "training_seed": cfg.get("training", {}).get("seed"),
            "gamma": cfg["runner"]["algorithm"].get("gamma"),
            "trained_forced_release": cfg["env"].get("forced_release", {}).get("probability"),
            "iteration": iteration, "envs": envs, "action_std": action_std,
            "mean": summarise(release_episodes(onnx_path, cfg["env"], envs, 0.0)),
            "sampled": summarise(release_episodes(onnx_path, cfg["env"], envs, action_std)),
            "gate_no_release": gate_no_release(src)}


def plot(rows: list[dict], path: Path) -> None:
    """Left: episodes without a release by target band, the mean (filled) against the sampled actor
    (open), per run. Right: the mean's median release time by band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bands = [b["band"] for b in rows[0]["mean"] if b["band"] != "all"]
    fig, (ax, at) = plt.subplots(1, 2, figsize=(11, 3.9))
    colors = plt.get_cmap("tab10")
    for j, r in enumerate(rows):
        x = np.arange(len(bands)) + (j - (len(rows) - 1) / 2) * 0.1
        label = f"{r['run'].replace('throw2d-', '')} (γ {r['gamma']})"
        for kind, marker in (("mean", "o"), ("sampled", "s")):
            y = [1 - b["released"] for b in r[kind] if b["band"] != "all"]
            ax.plot(x, y, marker, color=colors(j), mfc=colors(j) if kind == "mean" else "none", ms=6,
                    label=label if kind == "mean" else None)
        at.plot(x, [b["release_s_median"] for b in r["mean"] if b["band"] != "all"], "o-", color=colors(j), ms=5, label=label)
    for a, ylabel, title in ((ax, "episodes without a release", "no release within 10 s: actor's mean (filled), sampled (open)"),
                             (at, "median release command [s]", "when the actor's mean releases")):
        a.set_xticks(range(len(bands)), [f"targets {b}" for b in bands])
        a.set_ylabel(ylabel)
        a.set_title(title, fontsize=9)
        a.grid(axis="y", alpha=0.3)
    at.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    p = runs_parser(__doc__, "episodes per run and setting")
    p.add_argument("--action-std", type=float, default=ACTION_STD, help="noise std of the sampled actor")
    p.add_argument("--keep-rows-of", type=Path, default=None,
                   help="an earlier report (.json) of the same --envs and --action-std whose rows of other runs "
                        "stay in the new one, before the runs played now (each run takes minutes on a CPU)")
    a = p.parse_args()
    settings = {"envs": a.envs, "action_std": a.action_std, "key": RETURN_KEY}
    kept = kept_rows(a.keep_rows_of, settings, a.runs) if a.keep_rows_of else []
    rows = kept + rows_of(a.runs, lambda src, tmp: run_row(src, a.envs, a.action_std, tmp),
                          lambda r: f"{r['run']}: released {r['mean'][-1]['released']:.1%} (mean) / {r['sampled'][-1]['released']:.1%} (sampled)")
    write_report(a.out, rows, a.envs, a.action_std)


def write_report(out_stem: Path, rows: list[dict], envs: int, action_std: float) -> None:
    """``<out_stem>.json``, ``.md`` and ``.png`` of ``rows`` (:func:`run_row`'s, in order), played with
    ``envs`` episodes per run and setting and noise std ``action_std``."""
    out = {"date": datetime.now(UTC).isoformat(timespec="seconds"), "envs": envs, "key": RETURN_KEY,
           "action_std": action_std, "rows": rows}
    out_stem.parent.mkdir(parents=True, exist_ok=True)
    out_stem.with_suffix(".json").write_text(json.dumps(out, indent=1) + "\n")
    md = ["# 2D runs: releases of the actor's mean against the sampled actor", "",
          f"{envs} episodes per run and setting in the MJX training environment with the run's own randomisation "
          f"and targets, forced release off, PRNG key {RETURN_KEY}; `sampled` adds Gaussian noise of std {action_std} "
          "to every action entry, as PPO does in training. `flag quartiles`: the highest release flag the mean reached "
          f"in its unreleased episodes (threshold {RELEASE_THRESHOLD}).", "",
          "| run | seed | γ | forced release in training | iteration | targets | episodes | released (mean) | released (sampled) "
          "| landed (mean) | landed (sampled) | release time median (mean / sampled) [s] | unreleased flag quartiles | within 0.1 |",
          "|" + "---|" * 14]
    for r in rows:
        for bm, bs in zip(r["mean"], r["sampled"], strict=True):
            q = " / ".join(f"{v:.2f}" for v in bm["unreleased_flag_quartiles"]) or "-"
            within = f"{bm['unreleased_flag_within_0_1']:.0%}" if bm["unreleased"] else "-"
            md.append(f"| {r['run']} | {r['training_seed']} | {r['gamma']} | {r['trained_forced_release']} | {r['iteration']} "
                      f"| {bm['band']} | {bm['episodes']} | {bm['released']:.1%} | {bs['released']:.1%} | {bm['landed']:.1%} "
                      f"| {bs['landed']:.1%} | {bm['release_s_median']:.2f} / {bs['release_s_median']:.2f} | {q} | {within} |")
    md += gate_no_release_table(rows)
    out_stem.with_suffix(".md").write_text("\n".join(md) + "\n")
    plot(rows, out_stem.with_suffix(".png"))


if __name__ == "__main__":
    main()
