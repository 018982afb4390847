"""Adaptation of a policy version to a diagnosed site: ``slinger adapt``.

::

    slinger adapt --profile reports/diagnosis/m1/profile_fitted.json --policy policies/throw2d.onnx \\
                  --out var/adapted [--diagnosis reports/diagnosis/m1/report.json] [--method auto]

Input: a reality profile of the site (fitted by ``slinger diagnose``, or written by hand) and a
policy version. Output: a new policy version (ONNX + manifest) for that site:

* **aim correction** (any server, CPU only): for each target distance the commanded target that
  makes the MEAN impact under the profile hit it, found in the CPU twin by the evaluation
  protocol (sim_twin.evaluation.evaluate: the runtime's executor on the simulated machine under the
  profile): round 0 measures the bias of the unadapted policy, each further round aims at
  ``target - bias`` of the last table, with a secant step once two rounds give the local slope
  of impact against aim. When the site's logged throws of the base policy are at hand (the
  diagnosis' dataset), the table is then anchored to their measured impacts
  (sim_twin.adaptation.aim_anchor: what the fitted profile does not explain in closed loop is measured there
  and subtracted), so that a diagnosis naming a different, replay-equivalent effect still gives
  the right correction. The per-distance offset table goes into the manifest and is sealed
  into the ONNX metadata (runtime.aim); the runtime applies it before building the observation.
* **fine-tuning** (``--method finetune``/``auto`` with a GPU and a base checkpoint): PPO in MJX
  resumed from the base checkpoint with the profile's effects as FIXED randomisation
  (:func:`finetune_config`; effects MJX cannot represent are listed, and the aim correction
  is computed on top of the fine-tuned policy for them).

The manifest also carries ``site_profile`` (the profile, with the diagnosis' fitted 1 sigma as
its uncertainty when a report is given), which the server's previews of this version sample.
:func:`adapt` is the job-friendly entry point (no globals, progress callback, returns a dict).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from runtime.aim import AIM_FORMAT, ONNX_METADATA_KEY, canonical_json
from runtime.entrypoint import module_main
from runtime.policy import PolicyRunner, sha256_of, write_manifest
from sim_twin.twin.profile import RealityProfile

log = logging.getLogger(__name__)

DEFAULT_DISTANCES_M = {"2d": [7.0, 7.5, 8.0, 8.5, 9.0, 9.5, 10.0, 10.5], "3d": [6.5, 7.0, 7.5, 8.0, 8.5, 9.0, 9.5, 10.0]}
"""Table distances: the evaluation ranges (2D 7.5-10 m, 3D 7-9.5 m) plus one step either side."""


def seal_version(base_onnx: Path, out_onnx: Path, name: str, block: dict | None, site_profile: dict | None, adaptation: dict) -> Path:
    """Write a new policy version: the base ONNX graph with ``block`` sealed into its metadata
    and a manifest (the base's, renamed, with aim_correction, site_profile and
    training.adaptation). Returns out_onnx.

    Raises:
        runtime.policy.PolicyError: the result does not load in the runtime.
    """
    import onnx

    base_onnx, out_onnx = Path(base_onnx), Path(out_onnx)
    base = json.loads(base_onnx.with_suffix(".json").read_text())
    model = onnx.load(str(base_onnx))
    keep = [p for p in model.metadata_props if p.key != ONNX_METADATA_KEY]
    del model.metadata_props[:]
    model.metadata_props.extend(keep)
    if block is not None:
        model.metadata_props.add(key=ONNX_METADATA_KEY, value=canonical_json(block))
    out_onnx.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(out_onnx))
    manifest = {k: v for k, v in base.items() if k not in ("aim_correction", "site_profile")}
    manifest.update(name=name, onnx_sha256=sha256_of(out_onnx))
    if block is not None:
        manifest["aim_correction"] = block
    if site_profile is not None:
        manifest["site_profile"] = site_profile
    manifest["training"] = {**base.get("training", {}), "adaptation": adaptation}
    write_manifest(out_onnx, manifest)
    PolicyRunner.load(out_onnx)
    return out_onnx


def _table(distances, down, cross, **provenance) -> dict:
    return {"format": AIM_FORMAT, "distances_m": [float(d) for d in distances],
            "downrange_offset_m": [round(float(x), 4) for x in down], "crossrange_offset_m": [round(float(x), 4) for x in cross],
            **provenance}


def _measure(policy: Path, mode: str, profile_path: Path, distances, throws: int, seed: int, workers: int | None) -> dict:
    """Evaluation under the profile: {distance: (bias_m, mean_cross_m, landed, sigma_m)}."""
    from sim_twin.evaluation.evaluate import evaluate

    rep = evaluate(policy, mode, list(distances), throws, profile_path, seed=seed, workers=workers)
    return {t["target_m"]: (t["bias_m"], t["mean_crossrange_m"], t["landed"], t["sigma_downrange_m"]) for t in rep["targets"]}


def compute_aim_correction(policy_path: Path, profile: RealityProfile, distances_m: list[float] | None = None, throws: int = 30,
                           rounds: int = 2, seed: int = 11, workers: int | None = None,
                           progress: Callable[[str], None] | None = None) -> tuple[dict, list[dict]]:
    """The per-distance offsets that null the mean impact error under ``profile`` (module doc).

    Args:
        policy_path: the base policy version (ONNX with manifest beside it).
        profile: the site profile (its uncertainty block is ignored: the centre is aimed at).
        distances_m: table distances (default DEFAULT_DISTANCES_M of the mode).
        throws: twin throws per distance and round (bias standard error ~ sigma / sqrt(throws)).
        rounds: evaluation rounds (>= 1); the table returned is one step past the last one.
        seed: evaluation seed (every round uses other start poses).
        workers: processes (default: all cores).
        progress: called with a line per round.

    Returns:
        (table block, rounds history [{offsets, bias, mean_cross, landed, sigma}]).

    Raises:
        ValueError: no throw landed at some distance (the policy cannot serve this site there).
    """
    mode = PolicyRunner.load(policy_path).mode
    d = np.array(distances_m or DEFAULT_DISTANCES_M[mode], dtype=float)
    down, cross = np.zeros(len(d)), np.zeros(len(d))
    history: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        prof_path = Path(tmp) / "profile.json"
        prof_path.write_text(json.dumps({**profile.to_dict(), "uncertainty": {}}))
        for r in range(max(1, rounds)):
            cand = seal_version(Path(policy_path), Path(tmp) / f"round{r}.onnx", f"round{r}",
                                _table(d, down, cross) if r else None, None, {"round": r})
            res = _measure(cand, mode, prof_path, d, throws, seed + 1000 * r, workers)
            bias = np.array([res[x][0] if res[x][0] is not None else np.nan for x in d])
            mcross = np.array([res[x][1] if res[x][1] is not None else np.nan for x in d])
            if np.any(np.isnan(bias)):
                raise ValueError(f"no throw landed at {d[np.isnan(bias)].tolist()} m under profile {profile.name!r}")
            history.append({"round": r, "downrange_offset_m": down.tolist(), "crossrange_offset_m": cross.tolist(),
                            "bias_m": bias.tolist(), "mean_crossrange_m": mcross.tolist(),
                            "landed": [res[x][2] for x in d], "sigma_downrange_m": [res[x][3] for x in d]})
            msg = f"adapt round {r}: |bias| max {np.abs(bias).max():.3f} m (" + ", ".join(f"{x:g}: {b:+.3f}" for x, b in zip(d, bias)) + ")"
            log.info(msg)
            if progress:
                progress(msg)
            step_down, step_cross = -bias, -mcross
            if r:  # secant: the error moves by slope x aim change; trust the slope only near 1
                prev = history[-2]
                dd = down - np.array(prev["downrange_offset_m"])
                moved = np.abs(dd) > 0.02
                slope = np.where(moved, (bias - np.array(prev["bias_m"])) / np.where(moved, dd, 1.0), 1.0)
                step_down = -bias / np.where((slope > 0.5) & (slope < 1.5), slope, 1.0)
            down = down + step_down
            if mode == "3d":
                cross = cross + step_cross
    table = _table(d, down, cross, profile=profile.name, throws_per_round=throws, rounds=len(history),
                   base_version=PolicyRunner.load(policy_path).version)
    return table, history


def finetune_config(cfg: dict, profile: RealityProfile) -> tuple[dict, dict, list[str]]:
    """The training config with the profile's effects as fixed randomisation.

    Every randomisation range the config has for a quantity the profile sets becomes
    [value, value] (valve dead band / delay / lag as the mean over the four joints, release
    delay mean and std, passive friction as the viscous scale against the paper's value).

    The base config's ranges read by the critic's privileged normalisation are kept as
    ``env.privileged_ranges`` (sim_twin.training.privileged.trained_ranges; an existing entry, from an
    earlier fine-tuning, wins): the resumed critic was trained on inputs scaled over those ranges,
    and over the narrowed [v, v] every such input would read 0 instead of where v sits in them.

    Returns:
        (new config, {key: value fixed}, [effects or parameters MJX training cannot represent]).
    """
    import copy

    from sim_twin.training.privileged import trained_ranges
    from sim_twin.twin.physics import PAPER_VISCOUS_PER_S

    cfg = copy.deepcopy(cfg)
    rand = cfg["env"].setdefault("randomization", {})
    cfg["env"]["privileged_ranges"] = {**trained_ranges(rand), **cfg["env"].get("privileged_ranges", {})}
    stack = profile.stack()
    hp = stack.hydraulics(profile.hydraulics)
    mean_s, std_s = stack.release_delay(profile.release_delay_mean_s, profile.release_delay_std_s)
    viscous, _ = stack.passive_friction(profile.passive_viscous_per_s, profile.passive_coulomb_rad_per_s2)
    values = {"dead_band": float(np.mean(hp.dead_band)), "valve_delay_s": float(np.mean(hp.delay_s)), "lag_s": float(np.mean(hp.lag_s)),
              "friction_scale": viscous / PAPER_VISCOUS_PER_S, "release_delay_mean_s": float(mean_s), "release_delay_std_s": float(std_s)}
    fixed = {}
    for key, v in values.items():
        if key in rand:
            rand[key] = [v, v] if isinstance(rand[key], list) else v
            fixed[key] = v
    for key in ("release_delay_shift_s",):
        if key in rand:
            rand[key] = 0.0
    mapped = {"valve_dead_band", "valve_delay", "valve_lag", "release_delay", "passive_friction"}
    unsupported = [e.spec() for e in profile.effects if e.name not in mapped]
    return cfg, fixed, unsupported


def finetune(profile: RealityProfile, checkpoint: Path, config: Path | dict, out_onnx: Path, name: str, iterations: int = 200,
             num_envs: int | None = None, max_minutes: float | None = 8.0, log_dir: Path | None = None) -> tuple[Path, dict]:
    """Fine-tune in MJX (sim_twin.training.train) from ``checkpoint`` on the profile's effects. Returns
    (the exported ONNX, {fixed, unsupported, iterations, device})."""
    from sim_twin.training import train

    cfg = json.loads(Path(config).read_text()) if not isinstance(config, dict) else config
    new_cfg, fixed, unsupported = finetune_config(cfg, profile)
    log_dir = Path(log_dir or Path(out_onnx).parent / f"{name}-finetune")
    log_dir.mkdir(parents=True, exist_ok=True)
    cfg_path = log_dir / "finetune_config.json"
    cfg_path.write_text(json.dumps(new_cfg, indent=1))
    import torch

    if not torch.cuda.is_available():  # a checkpoint saved on the GPU: map it to the CPU first
        cpu_ckpt = log_dir / "base_checkpoint_cpu.pt"
        torch.save(torch.load(checkpoint, map_location="cpu", weights_only=False), cpu_ckpt)
        checkpoint = cpu_ckpt
    args = argparse.Namespace(mode=new_cfg["env"]["mode"], config=cfg_path, num_envs=num_envs, iterations=iterations,
                              chunk=min(25, iterations), max_minutes=max_minutes, log_dir=log_dir, tb_dir=None,
                              resume=Path(checkpoint), seed=1, keep_every=0, export=Path(out_onnx), name=name)
    train.run(args)
    return Path(out_onnx), {"fixed": fixed, "unsupported": unsupported, "iterations": iterations,
                            "device": "cuda" if torch.cuda.is_available() else "cpu", "log_dir": str(log_dir)}


def fitted_sigma(report: dict) -> dict[str, dict[str, float]]:
    """{effect: {param: 1 sigma}} of the effects a diagnosis report's fitted profile holds
    (``which`` entries; the named or best one, or every fitted one in a multi-effect report)."""
    out: dict[str, dict[str, float]] = {}
    for row in report.get("which", []):
        if row.get("sigma") and row.get("effect"):
            out.setdefault(row["effect"], {k: v for k, v in row["sigma"].items() if v is not None})
    return out


def adapt(profile: RealityProfile | dict | Path, policy_path: Path, out_dir: Path, name: str | None = None, method: str = "auto",
          diagnosis_report: dict | None = None, throws: int = 30, rounds: int = 2, distances_m: list[float] | None = None,
          checkpoint: Path | None = None, config: Path | None = None, workers: int | None = None,
          progress: Callable[[str], None] | None = None, logged: Path | None = None) -> dict:
    """Make a site-adapted policy version (module doc). Job-friendly: everything in arguments,
    files under ``out_dir``, progress by callback.

    Args:
        profile: the site profile (RealityProfile, its dict, or a JSON path).
        policy_path: the base version's ONNX (manifest beside it).
        out_dir: where ``<name>.onnx`` / ``.json`` and ``adaptation.json`` are written.
        name: the new version's name (default ``<base>-<profile>``).
        method: "aim" (CPU), "finetune" (needs a GPU, checkpoint and config) or "auto"
            (fine-tune when those are there, then aim-correct).
        diagnosis_report: the diagnosis' report.json: its fitted 1 sigma becomes the
            site profile's uncertainty (previews of the new version sample it).
        logged: the site's logged-throw dataset (sim_twin.diagnosis.dataset); default the
            diagnosis report's ``dataset`` when that directory still exists. Its throws of
            the base version anchor the aim table (sim_twin.adaptation.aim_anchor; not after fine-tuning,
            whose policy made no logged throws).

    Returns:
        {"policy": path, "manifest": {...}, "method", "history", "finetune", "wall_s"}.

    Raises:
        ValueError: unknown method, "finetune" without GPU/checkpoint/config, no landing.
    """
    from sim_twin.twin.uncertainty import with_fitted_sigma

    t0 = time.time()
    if method not in ("aim", "finetune", "auto"):
        raise ValueError(f"method must be aim, finetune or auto, got {method!r}")
    prof = profile if isinstance(profile, RealityProfile) else (
        RealityProfile.from_dict(profile) if isinstance(profile, dict) else RealityProfile.load(profile))
    base = PolicyRunner.load(policy_path)
    name = name or f"{base.version}-{prof.name}"
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    site = with_fitted_sigma(prof, fitted_sigma(diagnosis_report)) if diagnosis_report else prof
    ft = None
    source = Path(policy_path)
    if method == "finetune" and not (checkpoint and config):
        raise ValueError("fine-tuning needs the base version's --checkpoint and --config")
    if method == "finetune" or (method == "auto" and checkpoint and config and _has_gpu()):
        if not (checkpoint and config):
            raise ValueError("fine-tuning needs the base version's --checkpoint and --config")
        if not _has_gpu():
            log.warning("no GPU: fine-tuning on the CPU (use tiny settings)")
        source, ft = finetune(prof, checkpoint, config, out_dir / f"{name}-ft.onnx", f"{name}-ft")
        if progress:
            progress(f"fine-tuned in MJX ({ft['device']}); not representable there: {ft['unsupported'] or 'nothing'}")
    table, history = compute_aim_correction(source, prof, distances_m, throws, rounds, workers=workers, progress=progress)
    table, anchor = _anchor(table, history, base, logged, diagnosis_report, ft is not None, progress)
    adaptation = {"method": "finetune+aim" if ft else "aim", "profile": prof.to_dict(), "base_version": base.version,
                  "base_sha256": base.sha256, "history": history, "finetune": ft, "anchor": anchor,
                  "created_unix_s": time.time()}
    out = seal_version(source, out_dir / f"{name}.onnx", name, table, site.to_dict(), adaptation)
    manifest = json.loads(out.with_suffix(".json").read_text())
    result = {"policy": str(out), "name": name, "method": adaptation["method"], "aim_correction": table, "history": history,
              "finetune": ft, "anchor": anchor, "wall_s": time.time() - t0}
    (out_dir / f"{name}.adaptation.json").write_text(json.dumps(result, indent=1) + "\n")
    log.info("adapted version %s written: %s (%.0f s)", name, out, result["wall_s"])
    return {**result, "manifest": manifest}


def _anchor(table: dict, history: list[dict], base: PolicyRunner, logged: Path | None, report: dict | None, finetuned: bool,
            progress: Callable[[str], None] | None) -> tuple[dict, dict]:
    """The table anchored to the logged throws when there are any (sim_twin.adaptation.aim_anchor), and what was done."""
    from sim_twin.adaptation.aim_anchor import anchor_table, logged_errors

    if logged is None and report and report.get("dataset") and (Path(report["dataset"]) / "index.json").is_file():
        logged = Path(report["dataset"])
    if logged is None:
        return table, {"applied": False, "reason": "no logged throws given"}
    if finetuned:
        return table, {"applied": False, "reason": "fine-tuned policy: the logged throws are of the base version"}
    new, info = anchor_table(table, history, logged_errors(logged, base.version, base.mode), base.mode)
    info["dataset"] = str(logged)
    if progress and info["applied"]:
        progress(f"aim anchored to {info['throws']} logged throws: residual " + ", ".join(f"{v:+.3f}" for v in info["residual_down_m"]) + " m")
    return new, info


def _has_gpu() -> bool:
    try:
        import torch

        return bool(torch.cuda.is_available())
    except ImportError:
        return False


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--profile", type=Path, required=True, help="site reality profile (profile_fitted.json of `slinger diagnose`, or by hand)")
    parser.add_argument("--policy", type=Path, required=True, help="base policy version (ONNX, manifest beside it)")
    parser.add_argument("--out", type=Path, default=Path("var/adapted"), help="output directory")
    parser.add_argument("--name", default=None, help="new version name (default <base>-<profile>)")
    parser.add_argument("--method", choices=["aim", "finetune", "auto"], default="auto")
    parser.add_argument("--diagnosis", type=Path, default=None, help="the diagnosis' report.json (its fitted 1 sigma goes with the profile)")
    parser.add_argument("--throws", type=int, default=30, help="twin throws per distance and round")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--distances", default=None, help="table distances, e.g. 7:10.5:0.5 (default: the mode's evaluation range +- 0.5 m)")
    parser.add_argument("--checkpoint", type=Path, default=None, help="fine-tuning: the base version's checkpoint.pt")
    parser.add_argument("--config", type=Path, default=None, help="fine-tuning: its training config.json")
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--logged", type=Path, default=None,
                        help="the site's logged-throw dataset (default: the diagnosis report's dataset, when it exists): anchors the aim table")


def run(args: argparse.Namespace) -> int:
    from sim_twin.evaluation.cli import parse_targets

    report = json.loads(args.diagnosis.read_text()) if args.diagnosis else None
    res = adapt(args.profile, args.policy, args.out, args.name, args.method, report, args.throws, args.rounds,
                parse_targets(args.distances) if args.distances else None, args.checkpoint, args.config, args.workers,
                logged=args.logged)
    t = res["aim_correction"]
    print(f"{res['name']} ({res['method']}): {res['policy']}")
    for d, dr, cr in zip(t["distances_m"], t["downrange_offset_m"], t["crossrange_offset_m"]):
        print(f"  {d:5.2f} m: aim {dr:+.3f} m downrange, {cr:+.3f} m crossrange")
    return 0 if all(math.isfinite(x) for x in t["downrange_offset_m"]) else 1


def main(argv: list[str] | None = None) -> int:
    return module_main("slinger adapt", __doc__, build_parser, run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
