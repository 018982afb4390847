"""ROS 2 interoperability of the runtime.

* :mod:`runtime.ros2.types`: ROS 2 message types, CDR and type hashes from the ``rosbags``
  typestore (telemetry MCAP; the messages the nodes publish);
* :mod:`runtime.ros2.node`: rclpy nodes (the ``ros2`` extra or a ROS 2 installation): middleware
  by ``RMW_IMPLEMENTATION``, QoS, machine-local discovery, the one-publisher check of command topics;
* :mod:`runtime.ros2.config`: the bridge's topic, joint-name and unit mapping (pydantic, TOML/JSON/YAML);
* :mod:`runtime.ros2.bridge`: the machine bridge process (ROS 2 topics <-> Slinger machine interface).
"""
