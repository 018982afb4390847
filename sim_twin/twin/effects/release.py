"""Gripper opening delay: command -> payload free (paper Sec. III-F-1)."""

from __future__ import annotations

from sim_twin.twin.effects.base import Effect, Param


class ReleaseDelay(Effect):
    """Time from the gripper-open command to the payload being free, Gaussian per release.

    The simulated machine samples ``max(0, N(mean_s, jitter_s))`` at the command's rising edge
    and frees the payload at the first 10 ms step at or after it.
    """

    name = "release_delay"
    footprint = ("impact", "release")
    summary = "gripper opening delay (command to free payload): mean and jitter"
    stage = "release"
    params = (
        Param("mean_s", "s", 0.258, 0.0, 0.8, "mean opening delay, command to free fall",
              "paper Sec. III-F-1: 258 ms over 39 releases; range CHOSEN (slow gripper valves up to 0.8 s)"),
        Param("jitter_s", "s", 0.015, 0.0, 0.15, "standard deviation of the opening delay",
              "paper Sec. III-F-1: 15 ms; range CHOSEN", stochastic=True),
    )

    def release_delay(self, mean_s, std_s):
        return self.mean_s, self.jitter_s

    def estimate_spread(self, spreads: dict) -> dict:
        """jitter from the spread of logged opening delays (quantisation to 10 ms removed)."""
        s = spreads.get("release_delay_s")
        if s is None:
            return {}
        return {"jitter_s": float(max(s**2 - spreads.get("tick_s", 0.01) ** 2 / 12.0, 0.0) ** 0.5)}
