"""Start a PackML cell inside a ROS 2 installation:

    ros2 launch packml_ros2 cell.launch.py cell_file:=/path/to/cell.yaml

One process per node, the same nodes as `packml launch --processes` (packml_ros2.launcher.
node_specs): every unit, every configured EM (simulated by its `sim:` block) and the coordinator.
"""

from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from packml_ros2.launcher import node_specs, plan


def _nodes(context: LaunchContext) -> list[Node]:
    cell_file = LaunchConfiguration("cell_file").perform(context)
    specs = node_specs(plan(cell_file))  # validates the whole cell first (ConfigError names keys)
    return [
        Node(
            package="packml_ros2",
            executable=spec.executable,
            arguments=list(spec.arguments),
            name=None,  # names and namespaces come from the cell file
            output="screen",
            emulate_tty=True,
        )
        for spec in specs
    ]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "cell_file", description="the cell YAML (e.g. config/demo_cell.yaml)"
            ),
            OpaqueFunction(function=_nodes),
        ]
    )
