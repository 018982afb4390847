"""Figures of a diagnosis report (matplotlib, Agg): where.png, which.png, how_far.png."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from sim_twin.diagnosis.noise import PHASES

log = logging.getLogger(__name__)


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def where(report: dict, path: Path) -> None:
    """Chi-square per degree of freedom of every channel (nominal twin, all throws), by phase;
    1 = noise only, the dashed line is the gap threshold."""
    from sim_twin.diagnosis.noise import R_GAP

    plt = _plt()
    ch = report["where"]["channels"]
    names = list(ch)
    fig, ax = plt.subplots(figsize=(10, 0.28 * len(names) + 1.5))
    left = np.zeros(len(names))
    for p, color in zip(PHASES, ("tab:blue", "tab:orange", "tab:green")):
        v = np.array([ch[n]["by_phase"].get(p, {}).get("chi2", 0.0) / max(ch[n]["dof"], 1) for n in names])
        ax.barh(names, v, left=left, color=color, label=p)
        left += v
    ax.axvline(1.0, color="k", lw=0.8)
    ax.axvline(1.0 + R_GAP, color="k", ls="--", lw=0.8)
    ax.set_xscale("symlog", linthresh=2)
    ax.set_xlabel("chi-square / degrees of freedom (1 = within noise)")
    ax.invert_yaxis()
    ax.legend(fontsize=7)
    ax.set_title(f"Where: gap in {', '.join(report['where']['carriers'][:5]) or 'no channel'}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def which(report: dict, path: Path) -> None:
    """Bootstrap win frequency of every candidate per round (hatched: not admissible)."""
    plt = _plt()
    rounds = report["rounds"]
    fig, axes = plt.subplots(1, max(len(rounds), 1), figsize=(4.5 * max(len(rounds), 1), 4), squeeze=False)
    for ax, (i, r) in zip(axes[0], enumerate(rounds)):
        names = ["none"] + [c["effect"].split(":")[-1] for c in r["candidates"]]
        wins = [r["wins_none"]] + [c["wins"] for c in r["candidates"]]
        bars = ax.barh(names, wins, color=["grey"] + ["tab:green" if c["admissible"] else "tab:red" for c in r["candidates"]])
        for b, c in zip(bars[1:], r["candidates"]):
            if not c["admissible"]:
                b.set_hatch("//")
        ax.set_xlim(0, 1)
        ax.invert_yaxis()
        ax.set_xlabel("share of resamples won (held-out)")
        ax.set_title(f"round {i + 1}: {r['decision'][:40]}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def how_far(report: dict, path: Path) -> None:
    """Held-out chi-square per channel before and after the named effects."""
    plt = _plt()
    hf = report["how_far"]
    ch = hf["channels"]
    names = list(ch)
    y = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(9, 0.28 * len(names) + 1.5))
    ax.barh(y - 0.2, [ch[n]["chi2_before"] / max(ch[n]["dof"], 1) for n in names], 0.4, label="nominal twin", color="tab:red")
    ax.barh(y + 0.2, [ch[n]["chi2_after"] / max(ch[n]["dof"], 1) for n in names], 0.4, label="twin + named effects", color="tab:green")
    ax.set_yticks(y, names)
    ax.set_xscale("symlog", linthresh=2)
    ax.axvline(1.0, color="k", lw=0.8)
    ax.invert_yaxis()
    ax.legend(fontsize=7)
    imp = hf["impact_rms_m"]
    ax.set_title(f"How far (held-out throws): impact RMS {imp['before']:.3f} -> {imp['after']:.3f} m", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_all(report: dict, out: Path) -> dict[str, str]:
    """Write the figures that apply; returns {name: file name}."""
    files = {}
    for name, fn, needs in (("where", where, "where"), ("which", which, "rounds"), ("how_far", how_far, "how_far")):
        if report.get(needs):
            try:
                fn(report, out / f"{name}.png")
                files[name] = f"{name}.png"
            except Exception:  # a figure must never fail the diagnosis
                log.exception("plot %s failed", name)
    return files


def benchmark(result: dict, path: Path) -> Path:
    """Benchmark figure (``slinger diagnose benchmark`` JSON): left, the share of cases answered
    as the bar wants per kind (named / both named / unexplained-or-ambiguous / no gap) with the
    bars' targets; right, (fit - truth) / sigma of every compared parameter against the standard
    normal's 68 % band (calibrated 1 sigma puts ~68 % of the points inside |z| <= 1)."""
    plt = _plt()
    rows = result["cases"]
    kinds = [("single", 0.9), ("pair", 0.7), ("outside", 0.9), ("heldout", 0.9), ("noise", 0.9)]
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    shares, labels = [], []
    for k, bar in kinds:
        rs = [r for r in rows if r["kind"] == k]
        shares.append(sum(r["correct"] for r in rs) / len(rs) if rs else 0.0)
        labels.append(f"{k}\n({len(rs)})")
        a.plot([len(labels) - 1.4, len(labels) - 0.6], [bar, bar], "k--", lw=0.8)
    a.bar(labels, shares, color="tab:blue")
    a.set_ylim(0, 1.05)
    a.set_ylabel("share answered right (dashed: bar)")
    z = np.array([p["z"] for r in rows if r["correct"] for p in r["params"] if p.get("z") is not None], dtype=float)
    if len(z):
        b.axvspan(-1, 1, color="0.9")
        b.scatter(z, np.arange(len(z)), s=12)
        b.set_xlim(-max(4.0, np.abs(z).max() * 1.05), max(4.0, np.abs(z).max() * 1.05))
        b.set_xlabel(f"(fit - truth) / 1 sigma; inside |z| <= 1: {np.mean(np.abs(z) <= 1):.0%} of {len(z)}")
        b.set_yticks([])
    s = result["summary"]
    fig.suptitle(f"diagnosis benchmark: {s['cases']} of {result.get('cases_planned', s['cases'])} cases, seed {result['seed']}, "
                 f"{result['throws_per_case']} throws each" + ("" if result.get("complete") else " (PARTIAL)"))
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
