"""The paper's sim-to-sim check in a second engine: the deployed policy's evaluation on the Drake
machine (``slinger evaluate --engine drake``) beside the MuJoCo twin's, throw by throw.

The evaluation protocol (sim_twin.evaluation.evaluate) fixes every throw by its seed: the start pose, the
release-delay jitter and the measurement noise. The site matrix's nominal column
(``reports/site_matrix_<mode>.json``, seed 0, 100 throws per target, each throw's landing errors
in ``per_throw``) and a Drake evaluation at seed 0 therefore share their first N throws per
target, and :func:`compare_engines` pairs them: per target the MuJoCo figures on exactly the
throws Drake made, the Drake figures, the paired mean difference (Drake - MuJoCo) of the
downrange and crossrange errors with its standard error, and the nominal column's bars
(sim_twin.evaluation.matrix.cell_bars) judged in each engine. :func:`plot_engines` draws the paper's figure
(mean impact with 1 sigma bars against the target) for both engines side by side.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sim_twin.evaluation.matrix import cell_bars


def _stats(dr: np.ndarray, cr: np.ndarray, throws: int) -> dict:
    """summarise()-like statistics of landed throws' errors (m) out of ``throws``."""
    n = len(dr)
    return {"throws": throws, "landed": n, "success_rate": n / max(throws, 1),
            "bias_m": float(np.mean(dr)) if n else None, "sigma_downrange_m": float(np.std(dr)) if n else None,
            "mean_crossrange_m": float(np.mean(cr)) if n else None, "sigma_crossrange_m": float(np.std(cr)) if n else None}


def compare_engines(drake: dict, matrix: dict) -> dict:
    """Pair a Drake evaluation (sim_twin.evaluation.evaluate.evaluate with ``per_throw``) with the MuJoCo
    site matrix's nominal column on the same seeds.

    Args:
        drake: the Drake report (nominal profile; targets with ``per_throw``).
        matrix: a site-matrix report of the same policy version and mode (sim_twin.evaluation.matrix).

    Returns:
        {"mode", "policy_version", "throws_per_target", "targets": [{"target_m", "mujoco",
        "drake" (statistics and "bars"), "mujoco_full_column" (the matrix's own cell),
        "paired": {"n", "downrange_m", "downrange_se_m", "crossrange_m", "crossrange_se_m"}}]}.

    Raises:
        ValueError: other mode or policy version, another seed, a non-nominal Drake profile, no
            per-throw errors, or a Drake seed missing from the matrix.
    """
    for key in ("mode", "policy_version", "seed"):
        if drake.get(key) != matrix.get(key):
            raise ValueError(f"cannot pair: {key} {drake.get(key)!r} (Drake) against {matrix.get(key)!r} (site matrix)")
    if drake.get("profile") != "nominal":
        raise ValueError(f"the site matrix's nominal column pairs with a nominal evaluation, not profile {drake.get('profile')!r}")
    column = {round(t["target_m"], 6): t for t in next(p for p in matrix["profiles"] if p["name"] == "nominal")["targets"]}
    mode, rows = drake["mode"], []
    for t in drake["targets"]:
        cell = column.get(round(t["target_m"], 6))
        if cell is None or "per_throw" not in t or "per_throw" not in cell:
            raise ValueError(f"target {t['target_m']} m: no per-throw errors in both reports")
        mj = {s: (d, c) for s, d, c in zip(cell["per_throw"]["seed"], cell["per_throw"]["downrange_error_m"], cell["per_throw"]["crossrange_error_m"])}
        dk = list(zip(t["per_throw"]["seed"], t["per_throw"]["downrange_error_m"], t["per_throw"]["crossrange_error_m"]))
        missing = [s for s, _, _ in dk if s not in mj]
        if missing:
            raise ValueError(f"target {t['target_m']} m: seeds {missing[:5]} are not in the site matrix")
        out = {"target_m": t["target_m"]}
        for name, pairs in (("mujoco", [mj[s] for s, _, _ in dk]), ("drake", [(d, c) for _, d, c in dk])):
            landed = [(d, c) for d, c in pairs if d is not None]
            st = _stats(np.array([d for d, _ in landed]), np.array([c for _, c in landed]), len(pairs))
            st["bars"] = cell_bars(mode, "nominal", False, st) if landed else {"success": False, "accuracy": False}
            out[name] = st
        both = [(mj[s], (d, c)) for s, d, c in dk if d is not None and mj[s][0] is not None]
        diff = np.array([[b[0] - a[0], b[1] - a[1]] for a, b in both]).reshape(-1, 2)
        n = len(diff)
        se = diff.std(axis=0, ddof=1) / math.sqrt(n) if n > 1 else np.full(2, np.nan)
        out["paired"] = {"n": n, "downrange_m": float(diff[:, 0].mean()) if n else None, "downrange_se_m": float(se[0]),
                         "crossrange_m": float(diff[:, 1].mean()) if n else None, "crossrange_se_m": float(se[1])}
        out["mujoco_full_column"] = {k: cell[k] for k in ("throws", "success_rate", "bias_m", "sigma_downrange_m", "mean_crossrange_m", "sigma_crossrange_m")}
        rows.append(out)
    return {"mode": mode, "policy_version": drake["policy_version"], "throws_per_target": drake["throws_per_target"], "seed": drake["seed"],
            "targets": rows, "nominal_column_pass": {e: all(all(r[e]["bars"].values()) for r in rows) for e in ("mujoco", "drake")}}


def plot_engines(comparisons: list[dict], out: Path) -> Path:
    """The paper's figure for both engines: per comparison (mode) a panel with the mean impact
    and 1 sigma downrange bars against the target, MuJoCo and Drake side by side on the same
    throws. Returns ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(comparisons), figsize=(5.4 * len(comparisons), 4.4), squeeze=False)
    for ax, comp in zip(axes[0], comparisons):
        d = np.array([r["target_m"] for r in comp["targets"]])
        ax.plot([d.min() - 0.5, d.max() + 0.5], [d.min() - 0.5, d.max() + 0.5], "k--", lw=0.8, label="target")
        for k, (engine, fmt) in enumerate((("mujoco", "o"), ("drake", "s"))):
            rows = [r for r in comp["targets"] if r[engine]["landed"]]
            x = np.array([r["target_m"] for r in rows]) + (k - 0.5) * 0.1
            ax.errorbar(x, [r["target_m"] + r[engine]["bias_m"] for r in rows], yerr=[r[engine]["sigma_downrange_m"] for r in rows],
                        fmt=fmt, capsize=4, label=f"{engine}: mean impact ± 1σ downrange")
        ax.set_xlabel("target distance [m]")
        ax.set_ylabel("impact distance [m]")
        ax.set_title(f"{comp['mode'].upper()} {comp['policy_version']}: MuJoCo twin vs Drake,\n"
                     f"the same {comp['throws_per_target']} throws per target (seed {comp['seed']})", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def markdown(comp: dict) -> str:
    """The comparison as a Markdown table (bias and sigma per engine, paired difference)."""
    lines = [f"**{comp['mode'].upper()} `{comp['policy_version']}`**, the same {comp['throws_per_target']} throws per target in both engines "
             f"(seed {comp['seed']}); nominal column bars met: MuJoCo {comp['nominal_column_pass']['mujoco']}, Drake {comp['nominal_column_pass']['drake']}\n",
             "| target [m] | success MuJoCo / Drake | bias MuJoCo [m] | bias Drake [m] | σ down MuJoCo / Drake [m] | σ cross MuJoCo / Drake [m] "
             "| Drake − MuJoCo downrange [m] | Drake − MuJoCo crossrange [m] |",
             "|---|---|---|---|---|---|---|---|"]
    for r in comp["targets"]:
        m, k, p = r["mujoco"], r["drake"], r["paired"]

        def f(v, fmt="{:+.3f}"):
            return "n/a" if v is None else fmt.format(v)
        lines.append(f"| {r['target_m']:.1f} | {100 * m['success_rate']:.0f} / {100 * k['success_rate']:.0f} % | {f(m['bias_m'])} | {f(k['bias_m'])} | "
                     f"{f(m['sigma_downrange_m'], '{:.3f}')} / {f(k['sigma_downrange_m'], '{:.3f}')} | "
                     f"{f(m['sigma_crossrange_m'], '{:.3f}')} / {f(k['sigma_crossrange_m'], '{:.3f}')} | "
                     f"{f(p['downrange_m'])} ± {p['downrange_se_m']:.3f} | {f(p['crossrange_m'])} ± {p['crossrange_se_m']:.3f} |")
    return "\n".join(lines) + "\n"
