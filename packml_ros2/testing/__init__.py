"""Test support for packml_ros2 and for integrators' own tests: ROS domain isolation, in-process
nodes on a fresh context, nodes in separate OS processes, and bag replay checks.

The pytest plugin (:mod:`packml_ros2.testing.plugin`, registered as ``packml_ros2``) sets the
environment and provides the fixtures ``ros_domain``, ``ros`` and ``processes``.
"""
