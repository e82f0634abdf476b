"""The ROS shell of packml_ros2: what the engine looks like on ROS 2.

:mod:`.interface` declares a unit's interface once (its services and topics, their types, QoS and
latching); the unit node, the PLC bridge, the client proxies, the recorder and the README check
read it from there.
"""
