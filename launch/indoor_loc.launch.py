"""ROS 2 launch file equivalent to ``indoor-loc up config/bringup_example.yaml``.

Replays an imported PUTMC walk for user /walk01 in bag time through ``imu_node``, ``wifi_fix_node``
and ``pdr_kf_node`` and records every topic::

    ros2 launch indoor_loc indoor_loc.launch.py bag:=data/putmc/walk01.mcap \\
        radiomap:=data/putmc/radiomap out:=out/walk01_live.mcap user:=walk01

The params files are the package's ``config/*.yaml`` (installed to ``share/indoor_loc/config``).
Unlike ``indoor-loc up``, ``ros2 launch`` stops every node at once on Ctrl-C; the nodes still
process what they had received and publish their final outputs, but the recorder may stop before
``pdr_kf_node``'s final smoothed path arrives -- use ``indoor-loc up`` when that path matters.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, RegisterEventHandler
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    config = os.path.join(get_package_share_directory("indoor_loc"), "config")
    bag = LaunchConfiguration("bag")
    radiomap = LaunchConfiguration("radiomap")
    out = LaunchConfiguration("out")
    ns = LaunchConfiguration("user")      # a relative namespace: walk01 -> /walk01
    sim_time = {"use_sim_time": True}

    player = Node(package="indoor_loc", executable="player", name="player", output="screen",
                  # play once imu_node, wifi_fix_node and the recorder subscribe, then 2 s more for pdr_kf_node
                  arguments=[bag, "--clock", "--wait-for-subscribers", "60",
                             "--min-subscribers", "imu/data=2", "wifi/scan=2", "--delay", "2.0"],
                  parameters=[{"use_sim_time": False}])
    imu = Node(package="indoor_loc", executable="imu_node", namespace=ns, output="screen", respawn=True,
               respawn_delay=1.0,
               parameters=[os.path.join(config, "imu_node.yaml"), sim_time,
                           {"step_length_m": 0.7, "heading_source": "auto", "sensor_reliability": "reliable"}])
    wifi = Node(package="indoor_loc", executable="wifi_fix_node", namespace=ns, output="screen",
                parameters=[sim_time, {"radiomap": radiomap, "method": "wknn"}])
    pdr_kf = Node(package="indoor_loc", executable="pdr_kf_node", namespace=ns, output="screen",
                  parameters=[os.path.join(config, "pdr_kf_node.yaml"), sim_time, {"odom_hold_s": 5.0}])
    recorder = Node(package="indoor_loc", executable="recorder", name="recorder", output="screen",
                    arguments=["-a", "-o", out], parameters=[{"use_sim_time": False}])
    return LaunchDescription([
        DeclareLaunchArgument("bag", default_value="data/putmc/walk01.mcap", description="bag to play"),
        DeclareLaunchArgument("radiomap", default_value="data/putmc/radiomap",
                              description="radio map directory made by `indoor-loc import`"),
        DeclareLaunchArgument("out", default_value="out/walk01_live.mcap", description="bag to record"),
        DeclareLaunchArgument("user", default_value="walk01", description="user namespace (no slash)"),
        player, imu, wifi, pdr_kf, recorder,
        # the player is required: when the bag has been played, stop everything
        RegisterEventHandler(OnProcessExit(target_action=player, on_exit=[EmitEvent(event=Shutdown())])),
    ])
