"""Training curve: one CSV row per checkpoint chunk, and its plot (matplotlib).

Columns: FIELDS, then any further ones the training appends (``reward_<term>``: the mean of each
scaled reward term over the chunk, sim_twin.training.rewards).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

FIELDS = ["iteration", "wall_s", "mean_reward", "mean_episode_length", "landed_per_done", "failed_per_done", "impact_err_m",
          "action_std", "control_steps_per_s"]


class TrainingCurve:
    """Rows of FIELDS kept in memory and saved to ``path`` (CSV), appended across resumed runs."""

    def __init__(self, path: Path, rows: list[dict] | None = None):
        self.path = Path(path)
        self.rows = rows or []

    @classmethod
    def load_or_new(cls, path: Path) -> TrainingCurve:
        path = Path(path)
        if not path.exists():
            return cls(path)
        with open(path, newline="") as f:
            rows = [{k: float(v) for k, v in r.items() if v not in (None, "")} for r in csv.DictReader(f)]
        return cls(path, rows)

    def last_wall_s(self) -> float:
        return self.rows[-1]["wall_s"] if self.rows else 0.0

    def columns(self) -> list[str]:
        """FIELDS and every further column any row holds, in first-seen order."""
        cols = list(FIELDS)
        for r in self.rows:
            cols += [k for k in r if k not in cols]
        return cols

    def append(self, **row: float) -> None:
        self.rows.append({**{k: math.nan for k in FIELDS}, **{k: float(v) for k, v in row.items()}})

    def save(self) -> None:
        with open(self.path, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=self.columns(), restval="nan")
            w.writeheader()
            w.writerows(self.rows)

    def plot(self, out: Path, title: str = "") -> None:
        """Mean return, landed fraction, mean impact error, action std and every reward term's
        mean against wall time (PNG, one panel each)."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        if not self.rows:
            return
        t = [r["wall_s"] / 60 for r in self.rows]
        panels = [("mean_reward", "mean episode return"), ("landed_per_done", "episodes ending in a landing"),
                  ("impact_err_m", "mean impact error of landings [m]"), ("action_std", "mean action std")]
        terms = [k for k in self.columns() if k.startswith("reward_")]
        ncol = 4
        nrow = 1 + math.ceil(len(terms) / ncol)
        fig, axes = plt.subplots(nrow, ncol, figsize=(4.3 * ncol, 3.2 * nrow), squeeze=False)
        items = panels + [(k, f"reward term {k[len('reward_'):]} (mean per step)") for k in terms]
        for ax in axes.flat[len(items):]:
            ax.axis("off")
        for ax, (key, label) in zip(axes.flat, items):
            ax.plot(t, [r.get(key, math.nan) for r in self.rows], marker=".", ms=3)
            ax.set_xlabel("training wall time [min]")
            ax.set_title(label, fontsize=9)
            ax.grid(alpha=0.3)
        fig.suptitle(title)
        fig.tight_layout()
        fig.savefig(out, dpi=100)
        plt.close(fig)
