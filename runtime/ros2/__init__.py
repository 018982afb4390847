"""ROS 2 interoperability of the runtime (no ROS 2 installation needed).

* :mod:`runtime.ros2.types`: ROS 2 Jazzy message types, CDR and type hashes (RIHS01) from the
  ``rosbags`` typestore;
* :mod:`runtime.ros2.rmw_zenoh`: rmw_zenoh's Zenoh key expressions, liveliness tokens and
  publication attachments, so that a Zenoh session talks to ROS 2 nodes run with
  ``RMW_IMPLEMENTATION=rmw_zenoh_cpp``;
* :mod:`runtime.ros2.config`: the bridge's topic, joint-name and unit mapping (pydantic, TOML/JSON/YAML);
* :mod:`runtime.ros2.bridge`: the machine bridge process (ROS 2 topics <-> Slinger machine interface).
"""
