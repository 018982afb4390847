"""The spread-sources benchmark's cell summary (tests/benchmarks/spread_sources.py): first-swing and
later-swing throws are told apart by the release command's time, and each group's spread and mean
error are reported, so that two release swings with different mean landings show as such."""

import numpy as np
import pytest

from tests.benchmarks.spread_sources import FIRST_SWING_S, cell


def _row(seed: int, err: float, release_s: float) -> dict:
    return {"seed": seed, "status": "landed", "downrange_error_m": err, "release_after_s": release_s,
            "opening_delay_s": 0.26, "start_q": [0.0] * 6, "release_sensitivity_mps": 1.0}


def test_cell_splits_first_and_later_swing_throws_and_gives_each_its_mean_and_sigma():
    rows = [_row(0, -0.10, 1.2), _row(1, -0.20, 1.4), _row(2, 0.05, 3.5), _row(3, 0.07, 3.7), _row(4, 0.06, 3.6),
            {"seed": 5, "status": "collision"}]
    c = cell(rows)
    assert (c["throws"], c["landed"], c["first_swing_throws"]) == (6, 5, 2)
    assert c["bias_first_swing_m"] == pytest.approx(-0.15) and c["bias_later_m"] == pytest.approx(0.06)
    assert c["sigma_first_swing_m"] == pytest.approx(0.0707, abs=1e-4) and c["sigma_later_m"] == pytest.approx(0.01)
    # the two swings' different means make the cell's spread larger than either group's
    assert c["sigma_downrange_m"] > max(c["sigma_first_swing_m"], c["sigma_later_m"])
    assert len(c["rows"]) == 6


def test_a_cell_with_no_first_swing_throw_has_no_first_swing_mean_or_sigma():
    c = cell([_row(0, 0.01, FIRST_SWING_S + 0.5), _row(1, 0.03, 4.0), _row(2, 0.01, 3.0), _row(3, 0.03, 3.5)])
    assert (c["first_swing_throws"], c["bias_first_swing_m"], c["sigma_first_swing_m"]) == (0, None, None)
    assert c["bias_later_m"] == pytest.approx(0.02)


def test_start_pose_offset_compares_each_groups_start_poses_with_the_cells_typical_one():
    from tests.benchmarks.spread_sources import start_pose_offset

    central = [[0.0, -0.9, 1.4, 0.8, -0.6, 0.0]] * 3
    outlying = [[0.0, -0.3, 2.5, 1.6, -1.5, 0.0], [0.0, -1.15, 0.8, 0.1, 0.1, 0.0]]
    first = np.array([True, True, True, False, False])
    off = start_pose_offset(central + outlying, first)
    assert off["start_pose_offset_later"] > 2 * off["start_pose_offset_first"]
    assert start_pose_offset([], np.array([], dtype=bool)) == {"start_pose_offset_first": None, "start_pose_offset_later": None}
    assert start_pose_offset(central, np.array([False] * 3))["start_pose_offset_first"] is None
