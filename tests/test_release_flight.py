"""The release-flight probe (tests/benchmarks/release_flight.py): it reads a landed throw's release
from the simulated machine and flies it again under a site's air; the drag-free refly lands where
the twin's nominal throw landed, and the windy site's air takes the throw short and to the wind's
side (docs/training.md, "What the site's air takes from a throw")."""

from pathlib import Path

import numpy as np
import pytest

from tests.benchmarks.release_flight import WINDY, flights, summary

ROOT = Path(__file__).resolve().parents[1]


def test_a_landed_throw_flown_again_under_the_windy_sites_air_lands_short_and_downwind():
    from sim_twin.twin.profile import RealityProfile

    air = RealityProfile.load(WINDY).stack()
    rows = flights(ROOT / "policies" / "throw2d.onnx", 9.0, [300000, 300001], air)
    assert len(rows) == 2
    for r in rows:
        assert 1.0 < r["speed_mps"] < 20.0 and -30.0 < r["elevation_deg"] < 80.0 and 0.3 < r["flight_s"] < 3.0
        assert r["air_downrange_m"] < -0.02  # drag (Cd 0.5) takes the throw short
        assert r["air_crossrange_m"] > 0.02  # the cross wind blows along +y, the left of a throw along +x
        assert abs(r["downrange_error_m"]) < 0.5 and np.isfinite(r["release_after_s"])
    s = summary(rows)
    assert s["landed"] == 2 and s["air_downrange_m"] == pytest.approx(np.median([r["air_downrange_m"] for r in rows]), abs=1e-4)


def test_without_air_the_refly_takes_nothing():
    from sim_twin.twin.profile import RealityProfile

    rows = flights(ROOT / "policies" / "throw2d.onnx", 9.0, [300000], RealityProfile().stack())
    assert rows and abs(rows[0]["air_downrange_m"]) < 1e-9 and abs(rows[0]["air_crossrange_m"]) < 1e-9
