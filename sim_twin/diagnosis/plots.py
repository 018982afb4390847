"""Figures of a diagnosis report (matplotlib, Agg): where.png, traces.png, which.png, how_far.png."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from runtime.machine import JOINT_NAMES

log = logging.getLogger(__name__)


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def where(report: dict, path: Path) -> None:
    """Share of the gap per channel (top 10) and per phase."""
    plt = _plt()
    w = report["where"]["conditioned"]
    chans = sorted(w["channels"].items(), key=lambda kv: -kv[1].get("share", 0))[:10]
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 3.8), gridspec_kw={"width_ratios": [3, 1]})
    a.barh([c for c, _ in chans][::-1], [v.get("share", 0) for _, v in chans][::-1], color="tab:red")
    for i, (_c, v) in enumerate(chans[::-1]):
        a.text(v.get("share", 0), i, f" rms {v['rms']:.3g} {v['unit']}", va="center", fontsize=7)
    a.set_xlabel("share of the gap J (nominal twin, all throws)")
    a.set_xlim(0, 1.25)
    b.bar(list(w["phases"]), list(w["phases"].values()), color="tab:blue")
    b.set_ylabel("share of J")
    b.set_ylim(0, 1)
    fig.suptitle(f"Where: J = {w['J']:.3g} over {report['throws']} throws", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def traces(th, nominal, fitted, effect: str, path: Path) -> None:
    """Logged against replayed traces of one throw (nominal twin and twin + effect)."""
    plt = _plt()
    t = th.t_s
    L = len(t)
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5))
    panels = [(1, "q"), (2, "q"), (3, "q"), (4, "q"), (4, "qd")]
    for ax, (j, kind) in zip(axes.flat, panels):
        logged = th.q[:, j] if kind == "q" else th.qd[:, j]
        ax.plot(t, logged, "k", lw=1.6, label="logged")
        for rep, style, lab in ((nominal, "--", "nominal twin"), (fitted, ":", f"twin + {effect}")):
            arr = rep.meas_q if kind == "q" else rep.meas_qd
            ax.plot(t, arr[:L, j], style, lw=1.2, label=lab)
        ax.axvline(t[th.cmd_row], color="grey", lw=0.8)
        if th.open_row is not None:
            ax.axvline(t[th.open_row], color="grey", lw=0.8, ls="--")
        ax.set_title(f"{kind}.{JOINT_NAMES[j]}", fontsize=9)
        ax.set_xlabel("s since swing start", fontsize=8)
    ax = axes.flat[5]
    flight = th.payload_t_s >= (th.t_s[th.open_row] if th.open_row is not None else 0)
    ax.plot(th.payload_pos_m[:, 0], th.payload_pos_m[:, 2], "k", lw=1.6, label="logged")
    for rep, style, lab in ((nominal, "--", "nominal twin"), (fitted, ":", f"twin + {effect}")):
        ax.plot(rep.cond["pos_m"][flight, 0], rep.cond["pos_m"][flight, 2], style, label=lab)
        ax.plot(*rep.pred["impact_m"][[0, 2]], "x")
    ax.plot(th.impact_m[0], 0, "ko")
    ax.set_title("payload x-z (m); x = impact", fontsize=9)
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(f"Throw {th.throw_id}: logged vs replayed (lines: release command, opening)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def which(report: dict, path: Path) -> None:
    """Candidates' penalised held-out scores."""
    plt = _plt()
    c = report["which"]
    fig, ax = plt.subplots(figsize=(8, 0.35 * len(c) + 1.2))
    names = [r["effect"] for r in c][::-1]
    scores = [max(r["score"], -0.2) for r in c][::-1]
    colors = ["tab:green" if s >= report["thresholds"]["explained_score"] else "tab:grey" for s in scores]
    ax.barh(names, scores, color=colors)
    ax.axvline(report["thresholds"]["explained_score"], color="k", ls="--", lw=0.8)
    ax.set_xlim(-0.2, 1.05)
    ax.set_xlabel("held-out gap explained, penalised for parameters")
    ax.set_title(report["verdict"]["text"], fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def how_far(report: dict, path: Path) -> None:
    """Held-out channel RMS before/after (top channels) and accuracy per target distance."""
    plt = _plt()
    h = report["how_far"]
    shares = report["where"]["conditioned"]["channels"]
    top = sorted(h["channels"], key=lambda c: -shares.get(c, {}).get("share", 0))[:8]
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4))
    x = np.arange(len(top))
    a.bar(x - 0.2, [h["channels"][c]["rms_before"] / shares[c]["scale"] for c in top], 0.4, label="nominal twin")
    a.bar(x + 0.2, [h["channels"][c]["rms_after"] / shares[c]["scale"] for c in top], 0.4, label=f"+ {h['effect']}")
    a.set_xticks(x, top, rotation=30, ha="right", fontsize=7)
    a.set_yscale("log")
    a.set_ylabel("held-out RMS / channel scale")
    a.legend(fontsize=8)
    acc = h["accuracy"]
    for k, (key, lab, mk) in enumerate((("observed", "observed", "ko"), ("replayed_nominal", "nominal twin", "s"), ("replayed_fitted", f"+ {h['effect']}", "^"),
                                       ("closed_loop_nominal", "policy in nominal twin", "v"), ("closed_loop_fitted", "policy in fitted twin", "D"))):
        if key not in acc:
            continue
        d = sorted((s for s in acc[key] if acc[key][s].get("mean_downrange_m", acc[key][s].get("bias_m")) is not None), key=float)
        if not d:
            continue
        mean = [acc[key][s].get("mean_downrange_m", acc[key][s].get("bias_m")) for s in d]
        sig = [acc[key][s].get("sigma_downrange_m") or 0.0 for s in d]
        b.errorbar(np.array(d, dtype=float) + 0.04 * (k - 2), mean, yerr=sig, fmt=mk, capsize=3, label=lab)
    b.axhline(0, color="grey", lw=0.8)
    b.set_xlabel("target distance (m)")
    b.set_ylabel("downrange error (m), ±1σ")
    b.legend(fontsize=7)
    imp = h["impact_error_m"]
    fig.suptitle(f"How far (held out): J {h['J_before']:.3g} -> {h['J_after']:.3g}; impact error {imp['predicted_before']:.2f} -> {imp['predicted_after']:.2f} m", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_all(report: dict, throws, nominal_all, test, test_reps, out: Path) -> dict[str, str]:
    """All figures into ``out``; returns {name: file name}."""
    files = {}
    where(report, out / "where.png")
    files["where"] = "where.png"
    worst = int(np.argmax([np.sum((th.q - r.meas_q[: len(th.t_s)]) ** 2) + np.sum((th.impact_m - r.cond["impact_m"]) ** 2) for th, r in zip(test, test_reps[0])]))
    traces(test[worst], test_reps[0][worst], test_reps[1][worst], report["how_far"]["effect"], out / "traces.png")
    files["traces"] = "traces.png"
    which(report, out / "which.png")
    files["which"] = "which.png"
    how_far(report, out / "how_far.png")
    files["how_far"] = "how_far.png"
    return files
