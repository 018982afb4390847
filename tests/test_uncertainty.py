"""The uncertainty block of reality profiles (sim_twin.twin.uncertainty): parsing, drawing, fitted sigma."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sim_twin.twin.effects import make_effect
from sim_twin.preview.preview import DEFAULT_SITE_PROFILE, site_profile
from sim_twin.twin.profile import RealityProfile
from sim_twin.twin.uncertainty import StartUncertainty, parse, sample_profile, unit_points, with_fitted_sigma

BLOCK = {
    "hydraulics.delay_s": {"range": [0.03, 0.08]},
    "release_delay_mean_s": {"range": [0.24, 0.28]},
    "hanging_mass.gripper_mass_kg": {"sigma": 40.0},
    "payload_drag.drag_coefficient": {"range": [0.2, 0.6]},
    "start.imu_sigma_rad": 0.02,
}


def test_profile_round_trip_and_default_site_profile():
    prof = RealityProfile.from_dict({"name": "site", "uncertainty": BLOCK})
    again = RealityProfile.from_dict(json.loads(json.dumps(prof.to_dict())))
    assert again.uncertainty == BLOCK
    unc = parse(again.uncertainty)
    assert [p.path for p in unc.params] == list(BLOCK)[:4]
    assert unc.param_dims == 4 + 1 + 1 + 1
    assert unc.start == StartUncertainty(imu_sigma_rad=0.02)
    assert "uncertainty" not in RealityProfile().to_dict()  # old files stay as they were
    assert parse(site_profile().uncertainty).param_dims > 10  # the shipped default has ranges
    assert site_profile({"site_profile": prof.to_dict()}).name == "site"
    assert site_profile({}, DEFAULT_SITE_PROFILE).name == "nominal_uncertain"


@pytest.mark.parametrize(("block", "message"), [
    ({"nonsense": {"range": [0, 1]}}, "expected a profile scalar"),
    ({"warp_drive.speed": {"range": [0, 1]}}, "warp_drive"),
    ({"valve_lag.nope": {"sigma": 1}}, "has no parameter 'nope'"),
    ({"hydraulics.speed": {"range": [0, 1]}}, "hydraulics has"),
    ({"release_delay_mean_s": {"range": [0.3, 0.2]}}, "lo <= hi"),
    ({"release_delay_mean_s": {"range": [0.2, 0.3], "sigma": 0.1}}, "exactly one"),
    ({"release_delay_mean_s": {"sigma": -1}}, ">= 0"),
    ({"payload_drag.drag_coefficient": {"range": [0.0, 9.0]}}, "outside the allowed"),
    ({"hydraulics.lag_s": {"range": [[0.1, 0.1], [0.2, 0.2]]}}, "lists of 4"),
    ({"start.colour": 1.0}, "unknown start-state key"),
    ({"start.imu_sigma_rad": float("nan")}, "finite"),
])
def test_bad_uncertainty_is_refused_with_the_reason(block, message):
    with pytest.raises(ValueError, match=message):
        RealityProfile.from_dict({"uncertainty": block})


def test_draws_cover_the_ranges_and_leave_the_centre_alone():
    prof = RealityProfile.from_dict({"effects": [{"effect": "hanging_mass", "params": {"gripper_mass_kg": 1400}}], "uncertainty": BLOCK})
    unc = parse(prof.uncertainty)
    lo = sample_profile(prof, unc, np.zeros(unc.param_dims))
    hi = sample_profile(prof, unc, np.full(unc.param_dims, 1 - 1e-9))
    mid = sample_profile(prof, unc, np.full(unc.param_dims, 0.5))
    assert lo.hydraulics.delay_s == pytest.approx(np.full(4, 0.03), abs=1e-6)
    assert hi.hydraulics.delay_s == pytest.approx(np.full(4, 0.08), abs=1e-6)
    assert (lo.release_delay_mean_s, hi.release_delay_mean_s) == pytest.approx((0.24, 0.28), abs=1e-6)
    mass = {p.effects[0].gripper_mass_kg for p in (lo, mid, hi)}
    assert min(mass) < 1400 - 100 and max(mass) > 1400 + 100 and mid.effects[0].gripper_mass_kg == pytest.approx(1400)
    drag = [e for e in hi.effects if e.name == "payload_drag"]
    assert len(drag) == 1 and drag[0].drag_coefficient == pytest.approx(0.6)  # added: the profile had none
    assert prof.effects[0].gripper_mass_kg == 1400 and len(prof.effects) == 1 and lo.uncertainty == {}
    # per-joint draws differ between joints
    pts = unit_points(16, unc.param_dims, seed=1)
    delays = np.array([sample_profile(prof, unc, u).hydraulics.delay_s for u in pts])
    assert delays.min() >= 0.03 and delays.max() <= 0.08 and np.ptp(delays[0]) > 0
    assert np.all(np.ptp(delays, axis=0) > 0.03)  # Sobol points spread over the range


def test_fitted_sigma_becomes_gaussian_uncertainty():
    prof = RealityProfile(effects=[make_effect("release_delay", mean_s=0.34, jitter_s=0.03)])
    out = with_fitted_sigma(prof, {"release_delay": {"mean_s": 0.004, "jitter_s": float("nan")}, "valve_lag": {"lag_s": 0.0}})
    assert out.uncertainty == {"release_delay.mean_s": {"sigma": 0.004}}
    assert prof.uncertainty == {}


def test_start_state_perturbation():
    q, qd = np.array([0.1, -0.5, 1.5, 0.2, -1.0, 0.0]), np.zeros(6)
    start = StartUncertainty()
    q0, qd0 = start.perturb(q, qd, np.full(8, 0.5))
    assert q0 == pytest.approx(q) and qd0 == pytest.approx(qd)
    q1, qd1 = start.perturb(q, qd, np.array([0.9] * 6 + [1.0, 0.0]))
    assert np.all(q1[:4] - q[:4] > 0.001) and np.all(q1[4:] - q[4:] > 0.01)
    assert qd1[4] == pytest.approx(0.95 * 0.05) and qd1[5] == pytest.approx(-0.95 * 0.05)
    assert np.all(qd1[:4] == 0)
