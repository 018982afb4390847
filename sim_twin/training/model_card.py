"""Model card of a trained policy: how it was made and how it did on the site matrix.

Written beside the exported ONNX as ``<stem>.card.json`` and ``<stem>.card.md`` by
``slinger train`` (sim_twin.training.train) and folded into the policy manifest's ``training`` section.
"""

from __future__ import annotations

import hashlib
import json
import platform
from pathlib import Path

from sim_twin.provenance import git_commit


def config_sha256(cfg: dict) -> str:
    """SHA-256 of the training config as canonical JSON (sorted keys, no spaces)."""
    return hashlib.sha256(json.dumps(cfg, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def accelerator() -> str:
    """"<n> x <GPU name>" of the GPUs torch sees, or "CPU (<processor>)"."""
    import torch

    if torch.cuda.is_available():
        n = torch.cuda.device_count()
        return f"{n} x {torch.cuda.get_device_name(0)}"
    return f"CPU ({platform.processor() or platform.machine()})"


ACCELERATORS_FILE = "accelerators.json"
"""The run directory's record of what trained it: one segment per start of ``slinger train`` there."""


def record_accelerator(log_dir: Path, from_iteration: int, gpus: str, world_size: int) -> list[dict]:
    """Append the segment ``{from_iteration, accelerator, processes}`` to ``log_dir``'s
    ACCELERATORS_FILE (a fresh run starts it; a resumed run continues it, so a run that went from
    one lent machine to another keeps both) and return all segments, oldest first. Segments that
    start at or after ``from_iteration`` (iterations trained again after a resume from an older
    checkpoint) are dropped. Raises ValueError on a file that is not such a list."""
    path = Path(log_dir) / ACCELERATORS_FILE
    segments = json.loads(path.read_text()) if path.exists() else []
    if not isinstance(segments, list) or not all(isinstance(s, dict) and "from_iteration" in s for s in segments):
        raise ValueError(f"{path}: not a list of accelerator segments")
    segments = [s for s in segments if s["from_iteration"] < from_iteration]
    segments.append({"from_iteration": int(from_iteration), "accelerator": gpus, "processes": int(world_size)})
    path.write_text(json.dumps(segments, indent=2) + "\n")
    return segments


def describe_accelerators(segments: list[dict], to_iteration: int) -> str:
    """One line for the card: the accelerator alone when one kind trained every iteration to
    ``to_iteration``, else each with its iterations (consecutive segments of one kind merged), e.g. "1 x NVIDIA H100 (iterations 0-925),
    1 x NVIDIA H200 (925-950)". Segments that start at or after ``to_iteration`` are left out."""
    used: list[dict] = []
    for s in [s for s in segments if s["from_iteration"] < to_iteration] or segments[:1]:
        if not used or used[-1]["accelerator"] != s["accelerator"]:  # a resume on the same kind continues its segment
            used.append(s)
    if len(used) == 1:
        return used[0]["accelerator"]
    ends = [s["from_iteration"] for s in used[1:]] + [to_iteration]
    parts = [f"{s['accelerator']} ({'iterations ' if i == 0 else ''}{s['from_iteration']}-{end})"
             for i, (s, end) in enumerate(zip(used, ends))]
    return ", ".join(parts)


def build_card(*, command: str, cfg: dict, iteration: int, train_wall_s: float, verdict_wall_s: float | None,
               gpus: str, world_size: int, matrices: list[dict], bars_met: bool, policy_sha256: str,
               commit: str | None = None) -> dict:
    """The card as a dict (see write_card for the files). ``gpus``: the accelerator line
    (:func:`accelerator`, or :func:`describe_accelerators` for a run trained on more than one);
    ``commit``: the commit that trained it where that is not this checkout's (a card written after the
    run, sim_twin.training.late_export), by default :func:`sim_twin.provenance.git_commit`."""
    return {
        "command": command,
        "config_sha256": config_sha256(cfg),
        "git_commit": commit or git_commit(),
        "accelerator": gpus,
        "processes": world_size,
        "num_envs_per_process": cfg.get("num_envs"),
        "training_seed": cfg.get("training", {}).get("seed"),
        "iteration": iteration,
        "training_wall_s": round(train_wall_s, 1),
        "wall_s_to_verdict": None if verdict_wall_s is None else round(verdict_wall_s, 1),
        "bars_met": bars_met,
        "matrices": matrices,
        "onnx_sha256": policy_sha256,
    }


def card_paths(onnx_path: Path) -> tuple[Path, Path]:
    """(``<stem>.card.json``, ``<stem>.card.md``) beside the policy ``onnx_path``: where :func:`write_card` writes."""
    onnx_path = Path(onnx_path)
    return onnx_path.with_name(onnx_path.stem + ".card.json"), onnx_path.with_name(onnx_path.stem + ".card.md")


def write_card(onnx_path: Path, card: dict) -> tuple[Path, Path]:
    """Write ``<stem>.card.json`` and ``<stem>.card.md`` beside ``onnx_path`` (:func:`card_paths`); returns both paths."""
    onnx_path = Path(onnx_path)
    j, m = card_paths(onnx_path)
    j.write_text(json.dumps(card, indent=2) + "\n")
    lines = [
        f"# Model card: {onnx_path.name}", "",
        f"* bars met on every seed: **{'yes' if card['bars_met'] else 'no'}**",
        f"* command: `{card['command']}`",
        f"* config SHA-256: `{card['config_sha256']}`; commit `{card['git_commit']}`",
        f"* accelerator: {card['accelerator']}, {card['processes']} process(es) x {card['num_envs_per_process']} environments,"
        f" training seed {card['training_seed']}",
        f"* iteration {card['iteration']}, training wall time {card['training_wall_s'] / 60:.1f} min"
        + ("" if card["wall_s_to_verdict"] is None else f" (matrix verdict at {card['wall_s_to_verdict'] / 60:.1f} min)"),
        f"* ONNX SHA-256: `{card['onnx_sha256']}`", "",
        "| iteration | seed | all bars | cells missing a bar | matrix |", "|---|---|---|---|---|",
    ]
    for r in card["matrices"]:
        lines.append(f"| {r['iteration']} | {r['seed']} | {'yes' if r['passed'] else 'no'} | {r['missing_cells']} | {Path(r['matrix_path']).name} |")
    m.write_text("\n".join(lines) + "\n")
    return j, m


def attach_card(onnx_path: Path, cfg: dict, command: str, card: dict) -> dict:
    """Build the card of the exported policy ``onnx_path`` (:func:`build_card` with ``card``'s
    keyword arguments but the policy's SHA-256, which is read from the file), write it beside the
    policy (:func:`write_card`) and into its manifest's ``training.model_card``. Returns the card.

    Raises:
        FileNotFoundError: ``onnx_path`` or its manifest (``<stem>.json``) is missing.
        KeyError: the manifest has no ``training`` section (not written by sim_twin.training.export)."""
    from runtime.policy import sha256_of, write_manifest

    onnx_path = Path(onnx_path)
    c = build_card(command=command, cfg=cfg, policy_sha256=sha256_of(onnx_path), **card)
    write_card(onnx_path, c)
    manifest = json.loads(onnx_path.with_suffix(".json").read_text())
    manifest["training"]["model_card"] = c
    write_manifest(onnx_path, manifest)
    return c
