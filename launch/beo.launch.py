"""Launch the beo_ros node with config/beo.yaml.

    ros2 launch beo_ros beo.launch.py [params_file:=...] [namespace:=...] [log_level:=info]
        [input_topic:=/camera/object_cloud]

Needs the ``launch`` and ``launch_ros`` packages (a full ROS 2 install); without them run
``beo-node --ros-args --params-file config/beo.yaml`` instead.
"""
import os

try:
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node
except ImportError:  # launch / launch_ros are not installed (e.g. the pip-wheel venv)
    LaunchDescription = None


def default_params_file():
    """config/beo.yaml from the installed share directory, else from the source tree."""
    try:
        from ament_index_python.packages import get_package_share_directory
        path = os.path.join(get_package_share_directory('beo_ros'), 'config', 'beo.yaml')
        if os.path.isfile(path):
            return path
    except Exception:  # package not installed through ament
        pass
    return os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', 'config', 'beo.yaml')


def generate_launch_description():
    if LaunchDescription is None:
        raise RuntimeError('launch/launch_ros are not installed; run '
                           '`beo-node --ros-args --params-file config/beo.yaml` instead')
    args = [
        DeclareLaunchArgument('params_file', default_value=default_params_file(),
                              description='YAML file with the beo node parameters'),
        DeclareLaunchArgument('namespace', default_value='',
                              description='Namespace of the beo node'),
        DeclareLaunchArgument('log_level', default_value='info',
                              description='debug, info, warn, error or fatal'),
        DeclareLaunchArgument('input_topic', default_value='/beo/input',
                              description='Remap the default input topic /beo/input'),
    ]
    node = Node(
        package='beo_ros',
        executable='beo_node',
        name='beo',
        namespace=LaunchConfiguration('namespace'),
        parameters=[LaunchConfiguration('params_file')],
        remappings=[('/beo/input', LaunchConfiguration('input_topic'))],
        arguments=['--ros-args', '--log-level', LaunchConfiguration('log_level')],
        output='screen',
        emulate_tty=True,
    )
    return LaunchDescription(args + [node])
