"""Launch the beo_ros node with config/beo.yaml.

    ros2 launch beo_ros beo.launch.py [params_file:=...] [namespace:=...] [log_level:=info]
        [input_topic:=/camera/object_cloud] [model_dir:=/path/to/model_bank]

Needs the ``launch`` and ``launch_ros`` packages (a full ROS 2 install); without them run
``beo-node --ros-args --params-file config/beo.yaml`` instead.
"""
import os

try:
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument, OpaqueFunction
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node
    from launch_ros.parameter_descriptions import ParameterValue
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


def node_parameters(model_dir):
    """The node's parameters: the params file, then ``model_dir`` as an override only when
    it is given (non-empty), so a model_dir set in the params file is kept otherwise."""
    params = [LaunchConfiguration('params_file')]
    if model_dir:
        # value_type=str: a directory name that looks like a number stays a string
        params.append({'model_dir': ParameterValue(model_dir, value_type=str)})
    return params


def _beo_node(context):
    return [Node(
        package='beo_ros',
        executable='beo_node',
        name='beo',
        namespace=LaunchConfiguration('namespace'),
        parameters=node_parameters(LaunchConfiguration('model_dir').perform(context)),
        remappings=[('/beo/input', LaunchConfiguration('input_topic'))],
        ros_arguments=['--log-level', LaunchConfiguration('log_level')],
        output='screen',
        emulate_tty=True,
    )]


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
                              description='Topic to read instead of /beo/input: remaps /beo/input '
                                          "(the node's default input topic, the ~/input of a node "
                                          "named beo without namespace, and the only input_topics "
                                          'entry of config/beo.yaml). Other topics listed in the '
                                          'input_topics parameter are not remapped by this'),
        DeclareLaunchArgument('model_dir', default_value='',
                              description="Model bank directory, or a shipped model's name "
                                          "(tabletop_32); '' keeps the params file's model_dir "
                                          '(there, empty means the shipped modelnet10_32)'),
    ]
    return LaunchDescription(args + [OpaqueFunction(function=_beo_node)])
