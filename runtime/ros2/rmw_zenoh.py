"""ROS 2 over Zenoh the way rmw_zenoh_cpp does it: key expressions, liveliness tokens and
publication attachments, so that a plain Zenoh session exchanges messages with ROS 2 nodes run
with ``RMW_IMPLEMENTATION=rmw_zenoh_cpp`` (ROS 2 Jazzy and later).

Formats (rmw_zenoh ``docs/design.md``, "Topic and Service name mapping to Zenoh key expressions",
"Graph Cache" and "Publishers"):

* topic data: ``<domain_id>/<fully qualified name without the leading />/<DDS type name>/<type hash>``,
  e.g. ``0/joint_states/sensor_msgs::msg::dds_::JointState_/RIHS01_a13e…``; payload: the CDR
  serialisation (with its 4-byte encapsulation header);
* liveliness tokens: node ``@ros2_lv/<domain>/<zid>/<node_id>/<node_id>/NN/<enclave>/<namespace>/<node>``;
  publisher (``MP``) / subscription (``MS``) ``@ros2_lv/<domain>/<zid>/<node_id>/<entity_id>/<kind>/
  <enclave>/<namespace>/<node>/<mangled topic>/<DDS type name>/<type hash>/<qos>``, where a mangled
  name has every ``/`` replaced by ``%`` and an empty enclave or namespace is ``%``;
* attachment of every publication: sequence number (int64 LE), source timestamp (int64 LE, ns since
  the Unix epoch), GID length (1 byte, 16) and the publisher's 16-byte GID.

Type names and hashes come from the rosbags Jazzy typestore (runtime.ros2.types). The QoS part of
a token is the default profile (reliable, volatile, keep last 10: ``::,10:,:,:,,``). What no ROS 2
installation could check here is listed in docs/ros2.md.
"""

from __future__ import annotations

import logging
import re
import secrets
import struct
import threading
import time
from collections.abc import Callable

import zenoh

from runtime.ros2 import types as rt

log = logging.getLogger(__name__)

LIVELINESS_PREFIX = "@ros2_lv"
DEFAULT_QOS = "::,10:,:,:,,"
"""qos_to_keyexpr of the default profile (reliable, volatile, keep last, depth 10)."""
_NAME = re.compile(r"^/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$")
_ATTACHMENT = struct.Struct("<qqB16s")


def qualified_name(name: str, namespace: str = "") -> str:
    """The fully qualified ROS name ``/ns/name`` (a name starting with ``/`` is absolute).

    Raises:
        ValueError: not a valid ROS 2 topic or namespace name (letters, digits, ``_``, ``/``).
    """
    for part in (name, namespace):
        if part and not _NAME.match(part):
            raise ValueError(f"not a valid ROS 2 name: {part!r}")
    if not name:
        raise ValueError("empty ROS 2 name")
    if name.startswith("/"):
        return name
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    return f"{ns}/{name}"


def mangle(name: str) -> str:
    """``/`` -> ``%`` (an empty name is ``%``)."""
    return name.replace("/", "%") if name else "%"


def topic_key(domain_id: int, topic: str, typename: str, namespace: str = "") -> str:
    """The Zenoh key of a ROS 2 topic's data, e.g. ``0/joint_states/sensor_msgs::msg::dds_::JointState_/RIHS01_…``.

    Raises:
        ValueError: a bad topic name, domain id or type name.
    """
    if not 0 <= int(domain_id) <= 232:
        raise ValueError(f"ROS_DOMAIN_ID must be 0..232, got {domain_id}")
    return f"{int(domain_id)}/{qualified_name(topic, namespace)[1:]}/{rt.dds_type_name(typename)}/{rt.type_hash(typename)}"


def node_token(domain_id: int, zid: str, node_id: int, node: str, namespace: str = "") -> str:
    """Liveliness token key of a node (entity kind ``NN``)."""
    return f"{LIVELINESS_PREFIX}/{int(domain_id)}/{zid}/{node_id}/{node_id}/NN/%/{mangle(namespace.strip('/') and '/' + namespace.strip('/'))}/{node}"


def entity_token(domain_id: int, zid: str, node_id: int, entity_id: int, kind: str, node: str, topic: str, typename: str,
                 namespace: str = "", qos: str = DEFAULT_QOS) -> str:
    """Liveliness token key of a publisher (``MP``) or subscription (``MS``).

    Raises:
        ValueError: another kind, or a bad topic or type name.
    """
    if kind not in ("MP", "MS"):
        raise ValueError(f"entity kind must be MP or MS, got {kind!r}")
    ns = mangle(namespace.strip("/") and "/" + namespace.strip("/"))
    return (f"{LIVELINESS_PREFIX}/{int(domain_id)}/{zid}/{node_id}/{entity_id}/{kind}/%/{ns}/{node}/"
            f"{mangle(qualified_name(topic, namespace))}/{rt.dds_type_name(typename)}/{rt.type_hash(typename)}/{qos}")


def attachment(sequence: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """The 33-byte publication attachment (sequence, source timestamp, GID).

    Raises:
        ValueError: a GID that is not 16 bytes.
    """
    if len(gid) != 16:
        raise ValueError(f"a GID has 16 bytes, got {len(gid)}")
    return _ATTACHMENT.pack(int(sequence), int(source_timestamp_ns), 16, bytes(gid))


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence, source timestamp ns, GID) of a publication attachment.

    Raises:
        ValueError: not the 33-byte layout with a 16-byte GID.
    """
    if len(data) != _ATTACHMENT.size:
        raise ValueError(f"attachment of {len(data)} bytes, expected {_ATTACHMENT.size}")
    seq, ts, n, gid = _ATTACHMENT.unpack(data)
    if n != 16:
        raise ValueError(f"GID length {n}, expected 16")
    return seq, ts, gid


class RosPublisher:
    """A ROS 2 publisher on a Zenoh session (see :class:`RosNode.publisher`)."""

    def __init__(self, session: zenoh.Session, key: str, token_key: str, typename: str):
        self.key, self.typename = key, typename
        self.gid = secrets.token_bytes(16)
        self._seq = 0
        self._lock = threading.Lock()
        self._pub = session.declare_publisher(key)
        self._token = session.liveliness().declare_token(token_key)

    def publish(self, message) -> None:
        """Serialise ``message`` (CDR) and put it with the rmw_zenoh attachment."""
        with self._lock:
            self._seq += 1
            seq = self._seq
        self._pub.put(rt.serialize(message, self.typename), attachment=attachment(seq, time.time_ns(), self.gid))

    def undeclare(self) -> None:
        self._token.undeclare()
        self._pub.undeclare()


class RosSubscription:
    """A ROS 2 subscription on a Zenoh session (see :class:`RosNode.subscribe`)."""

    def __init__(self, session: zenoh.Session, key: str, token_key: str, typename: str, callback: Callable):
        self.key, self.typename = key, typename
        self.dropped = 0

        def on_sample(sample) -> None:
            try:
                message = rt.deserialize(sample.payload.to_bytes(), typename)
            except Exception as e:  # noqa: BLE001 malformed CDR: log and drop
                self.dropped += 1
                log.warning("dropping a malformed %s on %s: %s", typename, key, e)
                return
            callback(message)

        self._sub = session.declare_subscriber(key, on_sample)
        self._token = session.liveliness().declare_token(token_key)

    def undeclare(self) -> None:
        self._token.undeclare()
        self._sub.undeclare()


class RosNode:
    """A ROS 2 node on a Zenoh session, as rmw_zenoh_cpp shows one: its ``NN`` liveliness token,
    and per publisher / subscription an ``MP`` / ``MS`` token and the topic's data key.

    Args:
        session: an open Zenoh session (the node does not close it).
        name: node name; namespace: ROS namespace ("" = none); domain_id: ROS_DOMAIN_ID.
        node_id: the node's id within the session's context (0 for the first).
    """

    def __init__(self, session: zenoh.Session, name: str, namespace: str = "", domain_id: int = 0, node_id: int = 0):
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name or ""):
            raise ValueError(f"not a valid ROS 2 node name: {name!r}")
        self.session, self.name, self.namespace, self.domain_id, self.node_id = session, name, namespace, int(domain_id), node_id
        self.zid = str(session.zid())
        self._next_id = node_id + 1
        self._entities: list = []
        self._token = session.liveliness().declare_token(node_token(self.domain_id, self.zid, node_id, name, namespace))

    def _entity(self, kind: str, topic: str, typename: str) -> tuple[str, str]:
        eid, self._next_id = self._next_id, self._next_id + 1
        return (topic_key(self.domain_id, topic, typename, self.namespace),
                entity_token(self.domain_id, self.zid, self.node_id, eid, kind, self.name, topic, typename, self.namespace))

    def publisher(self, topic: str, typename: str) -> RosPublisher:
        """A publisher of ``typename`` messages on ``topic``."""
        pub = RosPublisher(self.session, *self._entity("MP", topic, typename), typename)
        self._entities.append(pub)
        return pub

    def subscribe(self, topic: str, typename: str, callback: Callable) -> RosSubscription:
        """Call ``callback(message)`` (a rosbags dataclass) for each ``typename`` message on
        ``topic``, from Zenoh's callback thread; malformed CDR is logged and dropped."""
        sub = RosSubscription(self.session, *self._entity("MS", topic, typename), typename, callback)
        self._entities.append(sub)
        return sub

    @property
    def keys(self) -> list[str]:
        """The Zenoh keys of the node's publishers and subscriptions."""
        return [e.key for e in self._entities]

    def close(self) -> None:
        """Undeclare every entity and the node's token."""
        for e in self._entities:
            e.undeclare()
        self._entities.clear()
        self._token.undeclare()
