"""How each 2D policy's throws fly, and how much of a site's air their flight alone takes.

``python tests/benchmarks/release_flight.py NAME=POLICY.onnx ... --out reports/<name>`` throws every
policy at the nominal twin's far targets (``--targets``, m, on the throwing axis), ``--throws`` throws
each from the seeds' random start poses (seeds as the site matrix's seed 0: target index x 100000 +
throw), by evaluation's own throw loop (sim_twin.evaluation.evaluate.throw_batch). For each landed
throw it takes the payload's release as the simulated machine flew it (the row's ``release_pos_m``
and ``release_vel_mps``, at the opening) and flies that same release
again under the air of a reality profile (``--air``, default the windy site: drag Cd 0.5 and a
5 m/s cross wind; the profile's other effects, which act before the release, are not applied).

The difference between that flight's landing and the drag-free one is what the air takes from a
throw whatever the policy does after the opening: it depends only on the release (speed, angle,
height, flight time). Writes ``<out>.json`` and ``<out>.md``: per policy and target the medians of
the release command's time after the swing's start [s], release speed [m/s], elevation [deg],
height [m], flight time [s], the air's downrange shift [m] (along the target direction; negative = short) and its
crossrange drift [m].
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
WINDY = REPO / "sim_twin" / "profiles" / "windy_site.json"


def flights(policy: Path, distance_m: float, seeds: list[int], air) -> list[dict]:
    """One row per landed throw of ``policy`` at ``distance_m`` on the nominal twin (2D), thrown by
    sim_twin.evaluation.evaluate.throw_batch: the release's speed, elevation and height, the flight
    and release-command times, and how far ``air`` (an EffectStack) moves the landing of that same
    release, downrange and across (RK4 flights, sim_twin.twin.effects.payload.integrate_flight)."""
    from sim_twin.evaluation.evaluate import target_on_axis, throw_batch
    from sim_twin.twin.effects.payload import integrate_flight

    target = target_on_axis("2d", distance_m)
    u = np.array(target[:2], float) / np.linalg.norm(target[:2])  # the target direction (downrange)
    accel = air.flight_accel if air.has("flight_accel") else None
    rows = []
    for r in throw_batch(policy, "2d", distance_m, seeds):
        if r["status"] != "landed" or "release_pos_m" not in r:
            continue
        p0, v0 = np.asarray(r["release_pos_m"], float), np.asarray(r["release_vel_mps"], float)
        *_, hit_air = integrate_flight(p0, v0, accel)
        *_, hit_free = integrate_flight(p0, v0, None)
        d = np.asarray(hit_air[:2]) - np.asarray(hit_free[:2])
        rows.append({
            "seed": r["seed"], **release_state(p0, v0), "flight_s": float(r["flight_s"]),
            "release_after_s": float("nan") if r["release_after_s"] is None else float(r["release_after_s"]),
            "air_downrange_m": float(d @ u), "air_crossrange_m": float(d[0] * -u[1] + d[1] * u[0]),
            "downrange_error_m": float(r["downrange_error_m"]),
        })
    return rows


def release_state(p0: np.ndarray, v0: np.ndarray) -> dict:
    """The payload's speed [m/s], elevation above the horizontal [deg] and height [m] at its release
    from ``p0`` (3,) m with ``v0`` (3,) m/s, machine frame."""
    return {"speed_mps": float(np.linalg.norm(v0)), "elevation_deg": float(np.degrees(np.arctan2(v0[2], np.linalg.norm(v0[:2])))),
            "height_m": float(p0[2])}


def summary(rows: list[dict]) -> dict:
    """Medians of the per-throw quantities (None where no throw landed)."""
    keys = ("release_after_s", "speed_mps", "elevation_deg", "height_m", "flight_s", "air_downrange_m", "air_crossrange_m", "downrange_error_m")
    return {"landed": len(rows), **{k: (round(statistics.median(r[k] for r in rows), 4) if rows else None) for k in keys}}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("policies", nargs="+", help="NAME=PATH of 2D ONNX policies")
    p.add_argument("--targets", default="8,9,10", help="target distances, m")
    p.add_argument("--throws", type=int, default=20)
    p.add_argument("--air", type=Path, default=WINDY, help="reality profile whose flight effects fly the releases again")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    from sim_twin.evaluation.evaluate import throw_seeds
    from sim_twin.provenance import git_commit
    from sim_twin.twin.profile import RealityProfile

    air = RealityProfile.load(args.air).stack()
    targets = [float(t) for t in args.targets.split(",")]
    results = []
    for spec in args.policies:
        name, path = spec.split("=", 1)
        for i, t in enumerate(targets):
            seeds = throw_seeds(0, int(round((t - 7.5) / 0.5)), args.throws)  # the 2D matrix's targets 7.5:10:0.5
            rows = flights(Path(path), t, seeds, air)
            s = summary(rows)
            results.append({"policy": name, "path": path, "target_m": t, **s, "throws": rows})
            print(name, t, s, flush=True)
    report = {"date": datetime.now(UTC).isoformat(timespec="seconds"), "commit": git_commit(), "host": platform.node(),
              "air": str(args.air.relative_to(REPO) if args.air.is_relative_to(REPO) else args.air), "throws_per_target": args.throws,
              "results": results}
    args.out.with_suffix(".json").write_text(json.dumps(report, indent=1) + "\n")
    md = ["# How the 2D policies' far throws fly, and what the site's air takes from them\n",
          f"Date {report['date']}, commit `{report['commit']}`, host {report['host']}. Nominal twin, {args.throws} throws per target "
          f"(seeds as the site matrix's seed 0); each landed throw's release flown again under `{report['air']}`'s flight effects. Medians.\n",
          "| policy | target | landed | release command | release speed | elevation | height | flight time | air: downrange | air: crossrange | downrange error (nominal) |",
          "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        def f(k, unit, nd=3):
            return "-" if r[k] is None else f"{r[k]:.{nd}g} {unit}".strip()
        md.append(f"| {r['policy']} | {r['target_m']:g} m | {r['landed']} | {f('release_after_s', 's')} | {f('speed_mps', 'm/s')} | {f('elevation_deg', '°')} | "
                  f"{f('height_m', 'm')} | {f('flight_s', 's')} | {f('air_downrange_m', 'm', 2)} | {f('air_crossrange_m', 'm', 2)} | "
                  f"{f('downrange_error_m', 'm', 2)} |")
    args.out.with_suffix(".md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
