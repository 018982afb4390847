"""Training curve: one CSV row per checkpoint chunk, and its plot (matplotlib)."""

from __future__ import annotations

import csv
import math
from pathlib import Path

FIELDS = ["iteration", "wall_s", "mean_reward", "mean_episode_length", "landed_per_done", "failed_per_done", "impact_err_m"]


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
            rows = [{k: float(v) for k, v in r.items()} for r in csv.DictReader(f)]
        return cls(path, rows)

    def last_wall_s(self) -> float:
        return self.rows[-1]["wall_s"] if self.rows else 0.0

    def append(self, **row: float) -> None:
        self.rows.append({k: float(row.get(k, math.nan)) for k in FIELDS})

    def save(self) -> None:
        with open(self.path, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=FIELDS)
            w.writeheader()
            w.writerows(self.rows)

    def plot(self, out: Path, title: str = "") -> None:
        """Mean reward, landed fraction and mean impact error against wall time (PNG)."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        if not self.rows:
            return
        t = [r["wall_s"] / 60 for r in self.rows]
        fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
        for ax, key, label in zip(
            axes,
            ("mean_reward", "landed_per_done", "impact_err_m"),
            ("mean episode return", "episodes ending in a landing", "mean impact error of landings [m]"),
        ):
            ax.plot(t, [r[key] for r in self.rows], marker=".")
            ax.set_xlabel("training wall time [min]")
            ax.set_title(label, fontsize=10)
            ax.grid(alpha=0.3)
        fig.suptitle(title)
        fig.tight_layout()
        fig.savefig(out, dpi=110)
        plt.close(fig)
