"""runtime.epoch_fence on its own: the two machine-side processes (the simulated machine's plant and
the ROS 2 bridge) share these, and their own tests check them in place (test_runtime_finality.py,
test_ros2_bridge.py)."""

import logging

from runtime.epoch_fence import EpochFence, WatchdogLatch, decode_for
from runtime.protocol.messages import ValveCommand, encode


def _cmd(epoch, u=(0.0, 0.0, 0.0, 0.2)):
    return ValveCommand(machine_id="m1", stamp_s=1.0, u=list(u), epoch=epoch)


def test_the_latch_holds_valves_neutral_after_a_trip_until_a_neutral_command(caplog):
    latch = WatchdogLatch()
    assert latch.armed and latch.trips == 0
    assert latch.admit([0.0, 0.5, 0.0, 0.0])  # armed: any command drives the valves
    latch.trip()
    assert not latch.armed and latch.trips == 1
    assert not latch.admit([0.0, 0.5, 0.0, 0.0])  # a late or resumed throw's command: held neutral
    assert not latch.admit([1e-9, 0.0, 0.0, 0.0])  # however small
    assert not latch.armed
    with caplog.at_level(logging.INFO, logger="runtime.epoch_fence"):
        assert latch.admit([0.0, 0.0, -0.0, 0.0])  # the runtime's neutral command: re-armed
    assert latch.armed and "re-armed" in caplog.text
    assert latch.admit([0.0, 0.5, 0.0, 0.0])
    latch.trip()
    latch.trip()
    assert latch.trips == 3  # counted, never reset (the runtime compares counts)


def test_the_fence_follows_the_newest_epoch_and_refuses_older_ones():
    fence = EpochFence()
    assert fence.admit(_cmd(None))  # before any epoch: an epoch-less command passes
    assert fence.admit(_cmd(5)) and fence.epoch == 5
    assert not fence.admit(_cmd(None))  # epoch-less once an epoch was seen
    assert not fence.admit(_cmd(4))
    assert fence.admit(_cmd(7)) and fence.epoch == 7  # a newer runtime takes over
    assert not fence.admit(_cmd(5))


def test_decode_for_drops_malformed_and_foreign_commands():
    assert decode_for(ValveCommand, encode(_cmd(1)), "m1").epoch == 1
    assert decode_for(ValveCommand, encode(_cmd(1)), "m2") is None
    assert decode_for(ValveCommand, b"{not json", "m1") is None
