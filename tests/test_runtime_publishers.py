"""The runtime's Zenoh publishers: the messages sent once ride lanes of their own (hazard RT14)."""

from __future__ import annotations

import zenoh

from runtime.node import declare_publishers
from runtime.protocol import keys
from runtime.zenoh_session import open_session


def test_one_shot_messages_have_their_own_priority_lanes():
    """The GripperCommand (sent on change only) and the AbortAck must not share the 100 Hz valve
    stream's queue, where a full queue drops samples; none of them may block the control loop."""
    with open_session("peer", listen=["tcp/127.0.0.1:0"]) as session:
        pubs = declare_publishers(session, "m1")
        try:
            assert set(pubs) == {keys.valve_cmd("m1"), keys.gripper_cmd("m1"), keys.status("m1"),
                                 keys.runtime_state("m1"), keys.estop_ack("m1")}
            valve, gripper, ack = pubs[keys.valve_cmd("m1")], pubs[keys.gripper_cmd("m1")], pubs[keys.estop_ack("m1")]
            assert valve.priority == zenoh.Priority.DATA
            assert gripper.priority == zenoh.Priority.INTERACTIVE_HIGH
            assert ack.priority == zenoh.Priority.REAL_TIME
            assert all(p.priority == zenoh.Priority.DATA for k, p in pubs.items() if k not in (keys.gripper_cmd("m1"), keys.estop_ack("m1")))
            assert all(p.congestion_control == zenoh.CongestionControl.DROP for p in pubs.values())
        finally:
            for p in pubs.values():
                p.undeclare()
