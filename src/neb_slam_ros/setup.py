"""Packaging of the ROS 2 nodes (ament_python): built by `colcon build`, run by `ros2 run neb_slam_ros <node>`."""

from glob import glob

from setuptools import setup

PACKAGE = "neb_slam_ros"
#: executable name -> module in neb_slam_ros exposing main() (neb_slam_ros/_launch.py lists the same)
NODES = ("tracker", "mapper", "loop_closer", "bag_replay", "slam")

setup(
    name=PACKAGE,
    version="0.1.0",
    description="NeB-SLAM ROS 2 nodes over neb_slam_core",
    license="MIT",
    packages=[PACKAGE],
    data_files=[
        # the ament index marker and the manifest: how `ros2 run` / `ros2 pkg` find the package
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        # what `ros2 launch neb_slam_ros <file>` and $(find-pkg-share neb_slam_ros) find
        (f"share/{PACKAGE}/launch", sorted(glob("launch/*.launch.xml"))),
        (f"share/{PACKAGE}/config", sorted(glob("config/*.yaml"))),
        (f"share/{PACKAGE}/rviz", sorted(glob("rviz/*.rviz"))),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    # through neb_slam_ros._launch, which handles a stop that arrives while the node's module imports
    entry_points={"console_scripts": [f"{node} = {PACKAGE}._launch:{node}" for node in NODES]},
)
