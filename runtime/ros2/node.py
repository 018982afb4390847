"""ROS 2 nodes on rclpy: the bridge's (runtime.ros2.bridge) and the simulated machine's
(sim_twin.twin.ros2_plant), on whatever middleware ``RMW_IMPLEMENTATION`` names (rmw_fastrtps_cpp,
Fast DDS, when unset; rmw_zenoh_cpp or rmw_cyclonedds_cpp where a site installed them).

* Message types are the rosidl packages' (``sensor_msgs``, ``std_msgs``, ``geometry_msgs``,
  ``nav_msgs``): publishers and subscriptions are declared with them, so the type names and RIHS01
  type hashes on the wire are those of the installed ROS 2 distribution. Outgoing messages are
  built with runtime.ros2.types (the rosbags typestore, which also writes the telemetry's MCAP) and
  published as their CDR bytes (``Publisher.publish(bytes)``); incoming ones arrive as rosidl
  messages (same field names).
* QoS (:data:`SENSOR_QOS` ... :data:`VALVE_QOS`) as ROS 2 drivers use it: sensor streams best
  effort, state streams and events reliable, valve commands reliable, keep last 1, with a 0.1 s
  deadline and automatic liveliness (0.5 s lease) offered, so a driver may watch both.
* Discovery is machine-local (:func:`machine_local_environment`): ``ROS_AUTOMATIC_DISCOVERY_RANGE``
  is set to ``LOCALHOST`` when unset; a wider range, static peers or a middleware configuration
  file are refused unless SROS2 is enforced (``ROS_SECURITY_ENABLE=true``,
  ``ROS_SECURITY_STRATEGY=Enforce``, ``ROS_SECURITY_KEYSTORE`` an existing directory). Whether the
  middleware can then do security is the middleware's to say at start (the Fast DDS of the
  PyPI ROS 2 wheels is built without it and refuses; docs/ros2.md).
* One publisher per command topic (:meth:`RosNode.command_publishers_fault`): a second
  publisher of valve or gripper commands is a fault (a stranger on the domain).

The node runs its own rclpy context (its domain id) and spins a single-threaded executor on a
background thread: callbacks run there, one at a time.
"""

from __future__ import annotations

import importlib
import logging
import os
import threading
from collections.abc import Callable, Iterable, MutableMapping
from pathlib import Path

from runtime.ros2 import types as rt

log = logging.getLogger(__name__)

RANGE_ENV = "ROS_AUTOMATIC_DISCOVERY_RANGE"
LOCAL_RANGES = ("LOCALHOST", "OFF")
WIDE_RANGES = ("SUBNET", "SYSTEM_DEFAULT")
WIDENING_ENV = ("ROS_STATIC_PEERS", "FASTDDS_DEFAULT_PROFILES_FILE", "FASTRTPS_DEFAULT_PROFILES_FILE",
                "ZENOH_SESSION_CONFIG_URI", "ZENOH_CONFIG_OVERRIDE")
"""Settings that can take discovery beyond this host (static peers, a Fast DDS XML profile, an
rmw_zenoh session configuration): refused without SROS2 enforced, like a wider range."""
VALVE_DEADLINE_S = 0.1
VALVE_LEASE_S = 0.5


class RosUnavailable(RuntimeError):
    """rclpy or a message package is not installed, or the middleware cannot start (the message says which)."""


class DomainRefused(RuntimeError):
    """The ROS 2 environment would open discovery beyond this host without SROS2 enforced."""


def secured(env: MutableMapping[str, str]) -> bool:
    """SROS2 enforced: ROS_SECURITY_ENABLE=true, ROS_SECURITY_STRATEGY=Enforce and
    ROS_SECURITY_KEYSTORE an existing directory."""
    keystore = env.get("ROS_SECURITY_KEYSTORE", "")
    return (env.get("ROS_SECURITY_ENABLE", "").lower() == "true" and env.get("ROS_SECURITY_STRATEGY", "") == "Enforce"
            and bool(keystore) and Path(keystore).is_dir())


def machine_local_environment(env: MutableMapping[str, str] | None = None) -> str:
    """Keep ROS 2 discovery on this host unless SROS2 is enforced; call before ``rclpy.init``
    (rcl reads the variables there). Sets ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` in ``env``
    (default ``os.environ``) when it is unset or empty.

    Returns:
        the discovery setting in words, for the start-up log.

    Raises:
        DomainRefused: a wider range (SUBNET, SYSTEM_DEFAULT), an unknown range value, or one of
        WIDENING_ENV set, without SROS2 enforced (:func:`secured`); the message names the
        setting and what allows it.
    """
    env = os.environ if env is None else env
    value = env.get(RANGE_ENV, "").strip().upper()
    if not value:
        env[RANGE_ENV] = value = "LOCALHOST"
    wider = []
    if value in WIDE_RANGES:
        wider.append(f"{RANGE_ENV}={value}")
    elif value not in LOCAL_RANGES:
        raise DomainRefused(f"{RANGE_ENV}={value!r} is not one of {LOCAL_RANGES + WIDE_RANGES}")
    wider += [f"{k} set" for k in WIDENING_ENV if env.get(k, "").strip()]
    if not wider:
        return f"discovery {value.lower()} (machine-local)"
    if not secured(env):
        raise DomainRefused(
            f"{', '.join(wider)}: ROS 2 discovery beyond this host lets any peer on that network publish valve "
            "commands; refused unless SROS2 is enforced (ROS_SECURITY_ENABLE=true, ROS_SECURITY_STRATEGY=Enforce, "
            f"ROS_SECURITY_KEYSTORE=<keystore directory>; docs/ros2.md). Use {RANGE_ENV}=LOCALHOST")
    return f"discovery {value.lower()} with {', '.join(wider)}, SROS2 enforced (keystore {env['ROS_SECURITY_KEYSTORE']})"


def message_class(typename: str):
    """The rosidl message class of ``typename`` (``pkg/msg/Name``).

    Raises:
        RosUnavailable: its package is not installed; ValueError: not a ``pkg/msg/Name`` name.
    """
    parts = typename.split("/")
    if len(parts) != 3 or parts[1] != "msg" or not all(parts):
        raise ValueError(f"not a ROS 2 message type name: {typename!r}")
    try:
        module = importlib.import_module(f"{parts[0]}.msg")
    except ImportError as e:
        raise RosUnavailable(f"ROS 2 message package {parts[0]} is not installed (pip install ros-{parts[0].replace('_', '-')}, "
                             f"or source a ROS 2 installation that has it): {e}") from e
    return getattr(module, parts[2])


def _qos():
    from rclpy.duration import Duration
    from rclpy.qos import (
        LivelinessPolicy,
        QoSProfile,
        ReliabilityPolicy,
        qos_profile_sensor_data,
    )

    return {
        "sensor": qos_profile_sensor_data,
        "state": QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE),
        "event": QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE),
        "valve": QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, deadline=Duration(seconds=VALVE_DEADLINE_S),
                            liveliness=LivelinessPolicy.AUTOMATIC, liveliness_lease_duration=Duration(seconds=VALVE_LEASE_S)),
    }


SENSOR_QOS = "sensor"
"""Best effort, keep last 5, volatile (rclpy's qos_profile_sensor_data): IMU, odometry; every
subscription of the bridge to the machine's streams (a best-effort reader matches both kinds of writer)."""
STATE_QOS = "state"
"""Reliable, keep last 10, volatile: joint states as ros2_control's joint_state_broadcaster
publishes them, the gripper state, the fault."""
EVENT_QOS = "event"
"""Reliable, keep last 10: events that must not be lost (the impact, the gripper command)."""
VALVE_QOS = "valve"
"""Reliable, keep last 1, deadline VALVE_DEADLINE_S, automatic liveliness with a VALVE_LEASE_S
lease: the valve commands (a driver that requests these sees a silent or dead bridge as a
missed deadline or lost liveliness)."""


class RosPublisher:
    """A publisher of one message type (see :meth:`RosNode.publisher`)."""

    def __init__(self, publisher, typename: str):
        self._pub, self.typename = publisher, typename

    def publish(self, message) -> None:
        """Publish a runtime.ros2.types message (a rosbags dataclass of this type) as CDR.

        Raises:
            TypeError: a message of another type.
        """
        if getattr(message, "__msgtype__", None) != self.typename:
            raise TypeError(f"publisher of {self.typename} got {getattr(message, '__msgtype__', type(message).__name__)}")
        self._pub.publish(rt.serialize(message, self.typename))

    @property
    def subscription_count(self) -> int:
        return self._pub.get_subscription_count()


class RosNode:
    """An rclpy node in its own context, spun on a background thread.

    Args:
        name: node name; namespace: ROS namespace ("" = none).
        domain_id: ROS_DOMAIN_ID (None: the environment's ROS_DOMAIN_ID, else 0).

    Raises:
        DomainRefused: discovery would reach beyond this host without SROS2 (machine_local_environment).
        RosUnavailable: rclpy is not installed, or the middleware refused to start (e.g. SROS2
        asked of a Fast DDS built without security).
    """

    def __init__(self, name: str, namespace: str = "", domain_id: int | None = None):
        self.discovery = machine_local_environment()
        try:
            import rclpy
            from rclpy.executors import SingleThreadedExecutor
        except ImportError as e:
            raise RosUnavailable(
                f"rclpy cannot be imported ({e}): install the ros2 extra (pip install 'slinger[ros2]') or source a ROS 2 "
                "installation; with the wheels, Python finds their libraries through the LD_LIBRARY_PATH that "
                "ros-wheels-bootstrapper sets when the environment's Python starts (a process started with "
                "_ROS_WHEELS_BOOTSTRAP_COMPLETE already set but without that LD_LIBRARY_PATH cannot load them)") from e
        self._qos = _qos()
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        try:
            self.node = rclpy.create_node(name, namespace=namespace or None, context=self.context,
                                          start_parameter_services=False)
        except Exception as e:
            self.context.try_shutdown()
            raise RosUnavailable(f"the ROS 2 middleware could not create node {name!r}: {e}") from e
        self.rmw = rclpy.get_rmw_implementation_identifier()
        self.domain_id = self.context.get_domain_id()
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, name=f"ros2-{name}", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass

    def qos(self, name: str):
        """The rclpy QoSProfile named SENSOR_QOS, STATE_QOS, EVENT_QOS or VALVE_QOS."""
        return self._qos[name]

    def publisher(self, topic: str, typename: str, qos: str) -> RosPublisher:
        """A publisher of ``typename`` (``pkg/msg/Name``) on ``topic`` with QoS ``qos``."""
        return RosPublisher(self.node.create_publisher(message_class(typename), topic, self._qos[qos]), typename)

    def subscribe(self, topic: str, typename: str, callback: Callable, qos: str,
                  on_deadline: Callable | None = None, on_liveliness: Callable | None = None):
        """Call ``callback(message)`` (a rosidl message; a callback of two parameters gets
        ``(message, info)``, rclpy's MessageInfo with ``publisher_gid``) for each message on
        ``topic``, on the executor's thread. ``on_deadline`` / ``on_liveliness``: rclpy's
        requested-deadline-missed and liveliness-changed events (with a QoS that has them)."""
        from rclpy.event_handler import SubscriptionEventCallbacks

        events = SubscriptionEventCallbacks(deadline=on_deadline, liveliness=on_liveliness)
        return self.node.create_subscription(message_class(typename), topic, callback, self._qos[qos], event_callbacks=events)

    def publishers_of(self, topic: str) -> list:
        """rclpy TopicEndpointInfo of every publisher of ``topic`` (relative names in the node's namespace)."""
        return self.node.get_publishers_info_by_topic(topic)

    def command_publishers_fault(self, topics: Iterable[str]) -> str | None:
        """None while each of ``topics`` has at most one publisher, else the fault in words
        (the topic and the publishing nodes)."""
        return next((f for f in (publishers_fault(topic, self.publishers_of(topic)) for topic in topics) if f), None)

    def close(self) -> None:
        """Stop spinning, destroy the node, shut the context down."""
        self.executor.shutdown(timeout_sec=5.0)
        self._thread.join(5.0)
        self.node.destroy_node()
        self.context.try_shutdown()


def publishers_fault(topic: str, infos: list) -> str | None:
    """None for at most one publisher (TopicEndpointInfo) of ``topic``, else the fault in words.

    A publisher whose node has not announced its name yet (DDS discovers the endpoint before
    the node's ``ros_discovery_info``; rclpy then reports ``_NODE_NAME_UNKNOWN_``) is named
    "an unnamed node"; the graph check repeats and the name fills in on a later finding."""
    if len(infos) <= 1:
        return None
    nodes = sorted(_node_label(i) for i in infos)
    return f"{len(infos)} publishers of {topic} ({', '.join(nodes)}), one expected"


def _node_label(info) -> str:
    """``namespace/name`` of a TopicEndpointInfo, or "an unnamed node" before discovery names it."""
    if "UNKNOWN" in info.node_name:
        return "an unnamed node"
    return f"{info.node_namespace.rstrip('/')}/{info.node_name}"


def gid_of(info) -> bytes:
    """The publisher GID of a MessageInfo (``info["publisher_gid"]["data"]``) or of a
    TopicEndpointInfo (``endpoint_gid``), as bytes comparable with each other."""
    if isinstance(info, dict):
        return bytes(info["publisher_gid"]["data"])[:16]
    return bytes(info.endpoint_gid)[:16]
