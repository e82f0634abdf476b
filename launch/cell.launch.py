"""Start a PackML cell inside a ROS 2 installation:

    ros2 launch packml_ros2 cell.launch.py cell_file:=/path/to/cell.yaml [sim:=true]

One process per node, the same nodes as `packml launch --processes` (packml_ros2.launcher.
node_specs): every unit, every EM as its entry says it runs (`sim:` simulated, `run:` your EM
class or program, `external:` started elsewhere: not here) and the coordinator. `sim:=true`
simulates every EM (a dry run of a real cell file).
"""

from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from packml_ros2.launcher import node_specs, plan


def _nodes(context: LaunchContext) -> list[Node | ExecuteProcess]:
    cell_file = LaunchConfiguration("cell_file").perform(context)
    simulate = LaunchConfiguration("sim").perform(context).lower() in ("true", "1", "yes")
    # validates the whole cell first (ConfigError names keys)
    specs = node_specs(plan(cell_file, simulate=simulate))
    return [
        ExecuteProcess(
            cmd=list(spec.argv),
            additional_env=dict(spec.env),
            name=spec.name.replace(" ", "_").replace("/", "_"),
            output="screen",
            emulate_tty=True,
        )
        if spec.argv
        else Node(
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
            DeclareLaunchArgument(
                "sim", default_value="false", description="simulate every EM (a dry run)"
            ),
            OpaqueFunction(function=_nodes),
        ]
    )
