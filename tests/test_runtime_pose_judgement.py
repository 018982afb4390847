"""RuntimeService judges a pose once (runtime.service.RuntimeService._pose_refusal): a machine at
rest publishes the same q and qd at 20 Hz and RuntimeInfo is built 20 times a second; a moved or
changed pose is judged again, so readiness still follows the machine."""

from __future__ import annotations

import numpy as np

import runtime.service as service_mod
from runtime.protocol.messages import RuntimeInfo, decode, encode
from tests.test_runtime_node import Harness, holding_path  # noqa: F401  (fixture)


def test_same_pose_is_judged_once_and_a_new_pose_again(holding_path, monkeypatch):  # noqa: F811
    calls = []
    real = service_mod.pose_refusal
    monkeypatch.setattr(service_mod, "pose_refusal", lambda st: (calls.append(st.stamp_s), real(st))[1])
    h = Harness(holding_path)
    h.tick()
    h.service.handle_info()
    state = h.twin.state()  # (one step on: a new pose)
    calls.clear()
    for k in range(5):  # the resting plant's re-stamped copies
        h.service.on_state(encode(state.model_copy(update={"stamp_s": state.stamp_s + 0.05 * k})))
        info = decode(RuntimeInfo, h.service.handle_info())
    assert len(calls) == 1 and info.ready, (calls, info.not_ready_reason)
    q = np.array(state.q)
    q[3] = 1.8  # telescope at its end
    h.service.on_state(encode(state.model_copy(update={"q": q.tolist(), "stamp_s": state.stamp_s + 1.0})))
    info = decode(RuntimeInfo, h.service.handle_info())
    assert len(calls) == 2 and not info.ready and info.not_ready_reason.startswith("joint at end"), info
    assert info.recovery == "return_to_ready"
