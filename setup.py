"""ament_python package `indoor_loc`; also installs with plain pip (see README)."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "indoor_loc"

# `ros2 run indoor_loc <exe>` executables (installed to lib/indoor_loc by setup.cfg under colcon,
# and to the venv's bin/ under pip, where a generic name would shadow another program's: vim's `view`,
# so the view and the map publisher are prefixed `indoor_loc_`; one name per node).
NODES = {
    "imu_node": "indoor_loc.nodes.imu_node:main",
    "wifi_scan_node": "indoor_loc.nodes.wifi_scan_node:main",
    "wifi_fix_node": "indoor_loc.nodes.wifi_fix_node:main",
    "recorder": "indoor_loc.nodes.recorder_node:main",
    "player": "indoor_loc.nodes.player_node:main",
    "pdr_kf_node": "indoor_loc.nodes.pdr_kf_node:main",
    "backend_node": "indoor_loc.nodes.backend_node:main",
    "indoor_loc_view": "indoor_loc.nodes.view_node:main",
    "indoor_loc_map": "indoor_loc.nodes.map_node:main",
    "tll_pf": "indoor_loc.nodes.tll_pf_node:main",
}

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    package_data={PACKAGE: ["data/*", "data/tf2_msgs/msg/*.msg"]},
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="indoor_loc maintainers",
    description="Indoor localisation from WiFi RSS and IMU on a building graph (ROS 2 Jazzy)",
    license="Apache-2.0",
    tests_require=["pytest"],
    python_requires=">=3.11",
    entry_points={
        "console_scripts": [f"{exe} = {target}" for exe, target in NODES.items()]
        + ["indoor-loc = indoor_loc.cli:main"],
    },
)
