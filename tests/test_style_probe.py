"""The checkpoint style probe (tests/benchmarks/training_style_probe.py): the nominal machine it
narrows the randomisation to, the recipe words, and, on two kept runs, that its reading agrees with
the site-matrix gate's, which throws in the CPU twin (docs/training.md "Why a 2D run stalls")."""

import json
import subprocess
from pathlib import Path

import pytest

pytest.importorskip("jax")
pytestmark = pytest.mark.torch  # the training extra (jax, mujoco-mjx, rsl_rl)

from sim_twin.training.config import CONFIG_DIR  # noqa: E402
from sim_twin.training.mjx_env import EnvConfig  # noqa: E402
from tests.benchmarks.training_style_probe import nominal_randomization, probe_run, recipe_of  # noqa: E402
from tests.benchmarks.training_throw_style import RunSource  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RUNS = ROOT / "policies" / "training"
PROBES_AT = "27dac7e0990367acc838115f9160f0dc789184af"
"""The last commit with the archived runs -ak to -ao (policies/training/ARCHIVE.md)."""
RECIPE = json.loads((CONFIG_DIR / "throw_2d.json").read_text())


def test_the_nominal_machine_is_the_twin_nominal_one_and_loads():
    from sim_twin.twin.hydraulics import NOMINAL_DELAY_S, NOMINAL_LAG_S
    from sim_twin.twin.profile import SensorParams

    rand = nominal_randomization(RECIPE["env"]["randomization"])
    env = EnvConfig.from_dict(dict(RECIPE["env"], randomization=rand))
    r = env.randomization
    assert r.valve_delay_s == (NOMINAL_DELAY_S, NOMINAL_DELAY_S) and r.lag_s == (NOMINAL_LAG_S, NOMINAL_LAG_S)
    assert r.velocity_scale == (1.0, 1.0) and r.friction_scale == (1.0, 1.0) and r.gripper_mass_scale == (1.0, 1.0)
    assert r.imu_latency_s == (SensorParams().imu_latency_s,) * 2 and r.release_delay_shift_s == 0.0
    assert RECIPE["env"]["randomization"]["valve_delay_s"] != [NOMINAL_DELAY_S] * 2  # the recipe itself is untouched


def test_recipe_words_name_what_a_run_changed():
    assert recipe_of(RECIPE) == "committed"
    cfg = json.loads(json.dumps(RECIPE))
    cfg["runner"]["algorithm"].update(gamma=1.0, use_mixed_precision=True)
    cfg["runner"]["torch_compile_mode"] = "default"
    cfg["env"]["far_targets"] = {"fraction": 0.5, "range_m": [9.0, 10.7]}
    assert recipe_of(cfg) == "γ 1.0, 50% far targets 9-10.7 m, bf16+compile"
    candidate = json.loads((CONFIG_DIR / "throw_2d_candidate.json").read_text())
    assert recipe_of(candidate) == ("γ 1.0, bf16+compile, float32 actor, no forced release, "
                                    "from it 300: err_3d 0.0 hold 0.01 hold_after_s 5.0")
    cfg["env"]["rewards"].update(err_3d=0.0, hold=0.01, hold_after_s=5.0)
    cfg["env"]["forced_release"]["probability"] = 0.0
    assert recipe_of(cfg).endswith("bf16+compile, no forced release, err_3d 0.0, hold 0.01 after 5 s")


@pytest.mark.parametrize("run, style", [("throw2d-scratch-ai", "long"), (f"{PROBES_AT}:policies/training/throw2d-scratch-ak", "short")])
def test_the_probe_reads_the_style_the_gate_read(run, style, tmp_path):
    if ":" in run:
        if subprocess.run(["git", "-C", str(ROOT), "cat-file", "-e", PROBES_AT], capture_output=True).returncode:
            pytest.skip(f"{PROBES_AT[:7]} is not in this clone's history (a shallow clone)")
        src = RunSource(run, repo=ROOT)
    else:
        src = RunSource(str(RUNS / run))
    row = probe_run(src, 10.0, 16, tmp_path)
    assert row["style"] == style == row["gate"]["style"]
    assert row["nominal"]["landed"] == 1.0 and row["training"]["landed"] > 0.9
    # the final checkpoint's nominal 10 m throw lasts what the gate's early matrix measured in the CPU twin
    assert abs(row["nominal"]["landing_s"] - row["gate"]["far_duration_s"]) < 0.3


def test_a_run_the_probe_cannot_read_is_refused_with_a_reason(tmp_path):
    run = tmp_path / "throw3d-x"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({**RECIPE, "env": {**RECIPE["env"], "mode": "3d"}}))
    with pytest.raises(ValueError, match="a 3d run; the probe reads 2D runs"):
        probe_run(RunSource(str(run)), 10.0, 4, tmp_path)
    (run / "config.json").write_text(json.dumps(RECIPE))
    with pytest.raises(FileNotFoundError, match="neither a checkpoint.pt nor an exported throw2d.onnx"):
        probe_run(RunSource(str(run)), 10.0, 4, tmp_path)
