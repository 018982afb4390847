"""The ROS 2 bridge's mapping: topics, joint names and units (a small TOML, JSON or YAML file).

Example (TOML; every key has the default shown unless marked)::

    domain_id = 0                       # ROS_DOMAIN_ID (default: none, i.e. the environment's ROS_DOMAIN_ID, else 0)
    namespace = ""                      # ROS namespace of the bridge node and of relative topic names
    node_name = "slinger_bridge"
    stale_after_s = 0.15                # a required topic older than this: machine link lost
    simulated = false                   # MachineState.simulated (true only for `slinger plant --ros2`)

    [topics]
    joint_states = "/joint_states"              # sensor_msgs/JointState: the active joints (encoders)
    passive_joint_states = ""                   # sensor_msgs/JointState of gripper_pitch/roll; "" = in joint_states
    imu = ""                                    # sensor_msgs/Imu on the gripper: the passive joints from it
                                                # (runtime.ros2.imu; wins over passive_joint_states)
    gripper_state = "/gripper/state"            # std_msgs/Bool, true = open (payload free)
    payload_attached = ""                       # std_msgs/Bool; "" = attached while the gripper is closed
    payload = ""                                # nav_msgs/Odometry of the payload (tracker); "" = none
    impact = "/payload/impact"                  # geometry_msgs/PointStamped, first ground contact; "" = none
    fault = ""                                  # std_msgs/String, why the machine cannot be commanded ("" = none)
    valve_command = "/valve_commands"           # std_msgs/Float64MultiArray (bridge -> machine)
    gripper_command = "/gripper/command"        # std_msgs/Bool, true = open (bridge -> machine)

    [joints.boom]                      # Slinger joint -> ROS joint name and units:
    name = "boom_joint"                # slinger value = ROS value * scale + offset (e.g. deg -> rad:
    scale = 0.0174533                  # scale = pi / 180); velocities: ROS velocity * scale
    offset = 0.0

    [valves.boom]                      # valve command u in [-1, 1] -> ROS array element:
    index = 1                          # data[index] = u * scale (e.g. scale = 100 for percent)
    scale = 1.0

Joints and valves not listed map to themselves: the Slinger joint name, scale 1, offset 0, and
ACTIVE_JOINTS order. :func:`load` reads a file; ``BridgeConfig()`` is the identity mapping.
"""

from __future__ import annotations

import json
import math
import re
import tomllib
from pathlib import Path
from typing import Annotated

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    model_validator,
)

from runtime.machine import ACTIVE_JOINTS, JOINT_NAMES, PASSIVE_JOINTS

_NAME = re.compile(r"^/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$")


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


def _topic(name: str) -> str:
    if name:
        qualified_name(name)  # raises ValueError for a bad name
    return name


Topic = Annotated[str, AfterValidator(_topic)]
Finite = Annotated[float, Field(allow_inf_nan=False)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class JointMap(_Strict):
    """One joint: its ROS name and ``slinger = ros * scale + offset`` (velocities: ``* scale``)."""

    name: Annotated[str, Field(min_length=1, max_length=128)]
    scale: Finite = 1.0
    offset: Finite = 0.0

    @model_validator(mode="after")
    def _nonzero(self):
        if self.scale == 0:
            raise ValueError("scale must not be 0")
        return self


class ValveMap(_Strict):
    """One valve: the element of the ROS command array and ``ros = u * scale``."""

    index: Annotated[int, Field(ge=0, lt=64)]
    scale: Finite = 1.0


class Topics(_Strict):
    """ROS topic names (absolute, or relative to the namespace); "" switches an optional one off."""

    joint_states: Topic = "/joint_states"
    passive_joint_states: Topic = ""
    imu: Topic = ""
    gripper_state: Topic = "/gripper/state"
    payload_attached: Topic = ""
    payload: Topic = ""
    impact: Topic = "/payload/impact"
    fault: Topic = ""
    valve_command: Topic = "/valve_commands"
    gripper_command: Topic = "/gripper/command"

    @model_validator(mode="after")
    def _required(self):
        for field in ("joint_states", "gripper_state", "valve_command", "gripper_command"):
            if not getattr(self, field):
                raise ValueError(f"topics.{field} is required")
        return self


class BridgeConfig(_Strict):
    """The bridge's mapping (module doc)."""

    domain_id: Annotated[int, Field(ge=0, le=232)] | None = None
    namespace: str = ""
    node_name: Annotated[str, Field(pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")] = "slinger_bridge"
    stale_after_s: Annotated[float, Field(gt=0.0, le=5.0)] = 0.15
    simulated: bool = False
    topics: Topics = Topics()
    joints: dict[str, JointMap] = {}
    valves: dict[str, ValveMap] = {}

    @model_validator(mode="after")
    def _names(self):
        if self.namespace:
            qualified_name("x", self.namespace)
        unknown = sorted(set(self.joints) - set(JOINT_NAMES)) + sorted(set(self.valves) - set(ACTIVE_JOINTS))
        if unknown:
            raise ValueError(f"unknown Slinger joints {unknown}: joints are {list(JOINT_NAMES)}, valves {list(ACTIVE_JOINTS)}")
        ros = [self.joint(j).name for j in JOINT_NAMES]
        if len(set(ros)) != len(ros):
            raise ValueError(f"two Slinger joints map to one ROS joint: {ros}")
        idx = [self.valve(j).index for j in ACTIVE_JOINTS]
        if len(set(idx)) != len(idx):
            raise ValueError(f"two valves map to one array element: {idx}")
        return self

    def joint(self, name: str) -> JointMap:
        """The mapping of Slinger joint ``name`` (identity unless configured)."""
        return self.joints.get(name) or JointMap(name=name)

    def valve(self, name: str) -> ValveMap:
        """The mapping of the valve of active joint ``name`` (its ACTIVE_JOINTS index unless configured)."""
        return self.valves.get(name) or ValveMap(index=ACTIVE_JOINTS.index(name))

    @property
    def valve_array_size(self) -> int:
        return 1 + max(self.valve(j).index for j in ACTIVE_JOINTS)

    @property
    def passive_topic(self) -> str:
        """The JointState topic the passive joints come on (the joint_states topic unless
        configured; unused when ``topics.imu`` is set)."""
        return self.topics.passive_joint_states or self.topics.joint_states

    def to_slinger(self, joints: tuple[str, ...], names: list[str], position, velocity) -> tuple[list[float], list[float]] | None:
        """Positions and velocities (rad, m, rad/s, m/s) of Slinger ``joints`` from a ROS
        JointState's ``names``, ``position`` and ``velocity`` (an empty velocity array: zeros),
        or None when a joint is missing or a value is not finite."""
        where = {n: i for i, n in enumerate(names)}
        q, qd = [], []
        for j in joints:
            m = self.joint(j)
            i = where.get(m.name)
            if i is None or i >= len(position):
                return None
            v = float(velocity[i]) if i < len(velocity) else 0.0
            q.append(float(position[i]) * m.scale + m.offset)
            qd.append(v * m.scale)
        return (q, qd) if all(math.isfinite(x) for x in q + qd) else None

    def to_ros(self, joints: tuple[str, ...], q, qd) -> tuple[list[str], list[float], list[float]]:
        """ROS names, positions and velocities of Slinger ``joints`` at ``q``, ``qd`` (inverse of :meth:`to_slinger`)."""
        maps = [self.joint(j) for j in joints]
        return ([m.name for m in maps], [(float(v) - m.offset) / m.scale for m, v in zip(maps, q)],
                [float(v) / m.scale for m, v in zip(maps, qd)])

    def valve_array(self, u) -> list[float]:
        """The ROS valve command array of ``u`` (4,) in ACTIVE_JOINTS order (unmapped elements 0)."""
        data = [0.0] * self.valve_array_size
        for j, v in zip(ACTIVE_JOINTS, u):
            m = self.valve(j)
            data[m.index] = float(v) * m.scale
        return data

    def valve_u(self, data) -> list[float] | None:
        """``u`` (4,) from a ROS valve command array (inverse of :meth:`valve_array`), or None if too short."""
        if len(data) < self.valve_array_size:
            return None
        return [float(data[self.valve(j).index]) / (self.valve(j).scale or 1.0) for j in ACTIVE_JOINTS]


class ConfigError(ValueError):
    """The bridge configuration file cannot be used (the message says which and why)."""


def load(path: str | Path, model: type[BridgeConfig] = BridgeConfig) -> BridgeConfig:
    """Read a bridge configuration (``.toml``, ``.json``, ``.yaml`` / ``.yml``) into ``model``
    (BridgeConfig or a subclass with more keys, e.g. the diagnosis' bag mapping).

    Raises:
        ConfigError: unreadable file, unknown suffix, syntax error or an invalid mapping.
    """
    path = Path(path)
    try:
        text = path.read_text()
        if path.suffix == ".toml":
            data = tomllib.loads(text)
        elif path.suffix == ".json":
            data = json.loads(text)
        elif path.suffix in (".yaml", ".yml"):
            from ruamel.yaml import YAML

            data = YAML(typ="safe").load(text)
        else:
            raise ConfigError(f"{path}: use a .toml, .json or .yaml file")
        return model.model_validate(data or {})
    except ConfigError:
        raise
    except ValidationError as e:
        problems = "; ".join(".".join(map(str, err["loc"])) + ": " + err["msg"] for err in e.errors())
        raise ConfigError(f"{path}: {problems}") from e
    except (OSError, ValueError) as e:
        raise ConfigError(f"{path}: {e}") from e


__all__ = ["PASSIVE_JOINTS", "BridgeConfig", "ConfigError", "JointMap", "Topics", "ValveMap", "load"]
