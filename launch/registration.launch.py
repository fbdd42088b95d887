"""Launch preop_loader_node + register_node with config/registration.yaml; optionally a bag, RViz and the Slicer bridge."""

import os

import yaml
from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import LifecycleNode, Node

from launch import LaunchDescription


def generate_launch_description():
    share = get_package_share_directory("liver_p2p_reg")
    params = os.path.join(share, "config", "registration.yaml")
    rviz_config = os.path.join(share, "config", "registration.rviz")
    with open(params) as f:  # the method's default comes from the one parameter file
        default_method = yaml.safe_load(f)["/**"]["ros__parameters"]["method"]
    model_path = LaunchConfiguration("model_path")
    fiducials_path = LaunchConfiguration("fiducials_path")
    bag = LaunchConfiguration("bag")
    managed = LaunchConfiguration("managed")
    # managed: the lifecycle executables, left unconfigured for the robot's supervisor to bring up in order
    plain_loader = PythonExpression(["'", model_path, "' != '' and '", managed, "'.lower() != 'true'"])
    managed_loader = PythonExpression(["'", model_path, "' != '' and '", managed, "'.lower() == 'true'"])
    loader_parameters = [
        {
            "model_path": model_path,
            "fiducials_path": fiducials_path,
            "mesh_path": LaunchConfiguration("mesh_path"),
            "frame_id": "ct",
            "units": LaunchConfiguration("units"),
            "structures_paths": LaunchConfiguration("structures"),
        }
    ]
    register_parameters = [params, {"method": LaunchConfiguration("method")}]
    play_bag = PythonExpression(["'", bag, "' != ''"])
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "model_path", default_value="", description="preop mesh/cloud in mm (PLY/STL/OBJ/VTK)"
            ),
            DeclareLaunchArgument("fiducials_path", default_value="", description="optional preop fiducials file (mm)"),
            DeclareLaunchArgument(
                "mesh_path", default_value="", description="optional closed mesh of a model given as points (mm)"
            ),
            DeclareLaunchArgument(
                "structures",
                default_value="",
                description="optional subsurface structures, comma-separated FILE[:LABEL] (mm, the ct frame)",
            ),
            DeclareLaunchArgument("units", default_value="mm", description="units of model_path: mm or m"),
            DeclareLaunchArgument("bag", default_value="", description="optional rosbag2 directory to play"),
            DeclareLaunchArgument("rviz", default_value="false", description="open RViz with config/registration.rviz"),
            DeclareLaunchArgument("method", default_value=default_method, description="registration method"),
            DeclareLaunchArgument(
                "slicer", default_value="false", description="serve the registration to 3D Slicer over OpenIGTLink"
            ),
            DeclareLaunchArgument("slicer_port", default_value="18944", description="OpenIGTLink port of the bridge"),
            DeclareLaunchArgument(
                "ct_convention", default_value="LPS", description="anatomical convention of the ct frame: LPS or RAS"
            ),
            DeclareLaunchArgument(
                "managed",
                default_value="false",
                description="start register_node and the loader as managed (lifecycle) nodes, unconfigured",
            ),
            Node(
                package="liver_p2p_reg",
                executable="preop_loader_node",
                name="preop_loader_node",
                parameters=loader_parameters,
                condition=IfCondition(plain_loader),
                output="screen",
            ),
            Node(
                package="liver_p2p_reg",
                executable="register_node",
                name="register_node",
                parameters=register_parameters,
                condition=UnlessCondition(managed),
                output="screen",
            ),
            LifecycleNode(
                package="liver_p2p_reg",
                executable="preop_loader_lifecycle_node",
                name="preop_loader_node",
                namespace="",
                parameters=loader_parameters,
                condition=IfCondition(managed_loader),
                output="screen",
            ),
            LifecycleNode(
                package="liver_p2p_reg",
                executable="register_lifecycle_node",
                name="register_node",
                namespace="",
                parameters=register_parameters,
                condition=IfCondition(managed),
                output="screen",
            ),
            Node(
                package="liver_p2p_reg",
                executable="slicer_bridge_node",
                name="slicer_bridge_node",
                parameters=[
                    {"port": LaunchConfiguration("slicer_port"), "ct_convention": LaunchConfiguration("ct_convention")}
                ],
                condition=IfCondition(LaunchConfiguration("slicer")),
                output="screen",
            ),
            ExecuteProcess(cmd=["ros2", "bag", "play", bag], condition=IfCondition(play_bag), output="screen"),
            Node(
                package="rviz2",
                executable="rviz2",
                arguments=["-d", rviz_config],
                condition=IfCondition(LaunchConfiguration("rviz")),
                output="screen",
            ),
        ]
    )
