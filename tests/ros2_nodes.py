"""Plain rclpy nodes for the ROS 2 tests, written against rclpy and the rosidl message packages
directly (not through runtime.ros2.node): what `ros2 topic echo`, a stranger's publisher and a
recorder (`ros2 bag record` to MCAP) do."""

from __future__ import annotations

import random
import threading
import time
from pathlib import Path

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

from runtime.ros2 import types as rt


def free_domain() -> int:
    """A ROS_DOMAIN_ID for one test (1..100: Fast DDS' ports of these stay below Linux' ephemeral range)."""
    return random.SystemRandom().randint(1, 100)


def message_type(typename: str):
    """The rosidl class of ``pkg/msg/Name``."""
    import importlib

    pkg, _msg, name = typename.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


class PlainNode:
    """An rclpy node in its own context on ``domain_id``, spun on a thread (context manager)."""

    def __init__(self, name: str, domain_id: int):
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.lock = threading.Lock()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass

    def __enter__(self) -> PlainNode:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.executor.shutdown(timeout_sec=5.0)
        self.thread.join(5.0)
        self.node.destroy_node()
        self.context.try_shutdown()

    def echo(self, topic: str, typename: str, qos=10) -> list:
        """(receive time s, message) of every message on ``topic``, appended as they come (the
        default QoS is what `ros2 topic echo` asks of a reliable publisher)."""
        got: list = []

        def cb(msg) -> None:
            with self.lock:
                got.append((time.time(), msg))

        self.node.create_subscription(message_type(typename), topic, cb, qos)
        return got

    def topic_types(self) -> dict[str, list[str]]:
        return dict(self.node.get_topic_names_and_types())


class Recorder(PlainNode):
    """Records raw CDR of the given topics, as `ros2 bag record` does, and writes one MCAP file
    (schemas ``ros2msg``, messages ``cdr``, log time = receive time)."""

    def __init__(self, domain_id: int, topics: dict[str, str], best_effort: tuple[str, ...] = ()):
        super().__init__("recorder", domain_id)
        self.topics = topics
        self.messages: list[tuple[str, int, bytes]] = []
        self.recording = False
        reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.subscriptions = {topic: self.node.create_subscription(message_type(typename), topic, self._cb(topic),
                                                                   qos_profile_sensor_data if topic in best_effort else reliable, raw=True)
                              for topic, typename in topics.items()}

    def wait_matched(self, timeout_s: float = 20.0) -> None:
        """Wait until every recorded topic's subscription has matched a publisher. A publisher seen
        in the graph by another node may not yet be matched with this one (Fast DDS matches endpoints
        per participant, later under load), and a volatile topic's messages sent before the match are
        never delivered: /gripper/command is sent only when the command changes. Raises TimeoutError naming
        the topics still unmatched."""
        deadline = time.monotonic() + timeout_s
        while (unmatched := sorted(t for t, sub in self.subscriptions.items() if sub.get_publisher_count() < 1)):
            if time.monotonic() > deadline:
                raise TimeoutError(f"the recorder matched no publisher of {unmatched} within {timeout_s:.0f} s")
            time.sleep(0.05)

    def _cb(self, topic: str):
        def cb(raw: bytes) -> None:
            if self.recording:
                with self.lock:
                    self.messages.append((topic, time.time_ns(), bytes(raw)))
        return cb

    def write(self, path: Path) -> int:
        """Write the recorded messages to ``path`` (.mcap); returns their count."""
        from mcap.writer import Writer

        with self.lock:
            messages = list(self.messages)
        with path.open("wb") as f:
            w = Writer(f)
            w.start(profile="ros2", library="slinger tests")
            channels = {}
            for topic, typename in self.topics.items():
                schema = w.register_schema(name=typename, encoding="ros2msg", data=rt.msgdef(typename).encode())
                channels[topic] = w.register_channel(topic=topic, message_encoding="cdr", schema_id=schema)
            for seq, (topic, t_ns, raw) in enumerate(messages):
                w.add_message(channels[topic], log_time=t_ns, data=raw, publish_time=t_ns, sequence=seq)
            w.finish()
        return len(messages)
