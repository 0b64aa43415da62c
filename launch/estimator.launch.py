"""Launch the kvark_ros estimator node (``kvark_estimator``).

    ros2 launch kvark_ros estimator.launch.py [config:=FILE] [namespace:=NS] [torque_source:=SOURCE]
                                              [joint_states:=TOPIC] [effort_commands:=TOPIC]

config         the estimator's parameter file (default: share/kvark_ros/config/panda.yaml); the same
               YAML that ``kvark train`` / ``kvark replay`` read (``kvark_estimator: ros__parameters:`` or
               ``/**/kvark_estimator: ros__parameters:``).
namespace      namespace of the node; its outputs are then /NS/kvark_estimator/..., and its relative
               inputs NS/joint_states, NS/effort_commands, NS/robot_description.
torque_source  input.torque_source: effort_commands (Float64MultiArray), effort_commands_joint_state
               (JointState effort) or joint_states_effort (the effort field of joint_states).
joint_states, effort_commands
               input.joint_states_topic and input.effort_commands_topic, e.g.
               joint_states:=franka/joint_states or effort_commands:=/forward_effort_controller/commands.

The last three default to '' (the config file's value).

The file's parameters are passed to the node as a parameter dictionary
(``kvark_ros.core.config.launch_parameters``) rather than as the file itself, so they apply under any
``namespace`` whatever the file's key; relative ``residual_model.model_dir``, ``robot_model.urdf`` and
``model_augmentation`` paths are resolved as ``kvark`` resolves them: against the folder holding the file.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from kvark_ros.core.config import NODE_NAME, launch_parameters

# launch argument -> key of the config's input group it overrides when not ''
INPUT_ARGUMENTS = (("torque_source", "torque_source"), ("joint_states", "joint_states_topic"),
                   ("effort_commands", "effort_commands_topic"))


def _estimator_node(context, *args, **kwargs):
    parameters = launch_parameters(LaunchConfiguration("config").perform(context))
    for argument, key in INPUT_ARGUMENTS:
        value = LaunchConfiguration(argument).perform(context)
        if value:
            parameters[f"input.{key}"] = value
    return [Node(package="kvark_ros", executable="estimator_node", name=NODE_NAME,
                 namespace=LaunchConfiguration("namespace"), parameters=[parameters],
                 output="screen", emulate_tty=True)]


def generate_launch_description() -> LaunchDescription:
    default_config = os.path.join(get_package_share_directory("kvark_ros"), "config", "panda.yaml")
    return LaunchDescription([
        DeclareLaunchArgument("config", default_value=default_config,
                              description="estimator parameter file (kvark_estimator: ros__parameters: ...)"),
        DeclareLaunchArgument("namespace", default_value="", description="namespace of the estimator node"),
        DeclareLaunchArgument("torque_source", default_value="",
                              description="input.torque_source: effort_commands | effort_commands_joint_state | "
                                          "joint_states_effort ('' = the config's)"),
        DeclareLaunchArgument("joint_states", default_value="",
                              description="input.joint_states_topic (sensor_msgs/JointState; '' = the config's)"),
        DeclareLaunchArgument("effort_commands", default_value="",
                              description="input.effort_commands_topic (Float64MultiArray or JointState; "
                                          "'' = the config's)"),
        OpaqueFunction(function=_estimator_node),
    ])
