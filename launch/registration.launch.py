"""Launch preop_loader_node + register_node with config/registration.yaml; optionally a bag, RViz and the Slicer bridge."""

import os

import yaml
from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node

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
    use_loader = PythonExpression(["'", model_path, "' != ''"])  # bags carry /preop/* themselves
    play_bag = PythonExpression(["'", bag, "' != ''"])
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "model_path", default_value="", description="preop mesh/cloud in mm (PLY/STL/OBJ/VTK)"
            ),
            DeclareLaunchArgument("fiducials_path", default_value="", description="optional preop fiducials file (mm)"),
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
            Node(
                package="liver_p2p_reg",
                executable="preop_loader_node",
                name="preop_loader_node",
                parameters=[
                    {
                        "model_path": model_path,
                        "fiducials_path": fiducials_path,
                        "frame_id": "ct",
                        "units": LaunchConfiguration("units"),
                    }
                ],
                condition=IfCondition(use_loader),
                output="screen",
            ),
            Node(
                package="liver_p2p_reg",
                executable="register_node",
                name="register_node",
                parameters=[params, {"method": LaunchConfiguration("method")}],
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
