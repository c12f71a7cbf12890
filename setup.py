"""ament_python build of neurncd_ros (colcon build, or pip install for the offline tool)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "neurncd_ros"
VERSION = "0.1.0"

# rosdep key (package.xml <exec_depend>) -> pip requirement name (requirements.txt).
# test_packaging checks that package.xml, this table and requirements.txt agree.
RUNTIME_DEPENDENCIES = {
    "rclpy": "ros-jazzy-rclpy",
    "rmw_fastrtps_cpp": "ros-jazzy-rmw-fastrtps-cpp",
    "sensor_msgs": "ros-jazzy-sensor-msgs",
    "geometry_msgs": "ros-jazzy-geometry-msgs",
    "std_msgs": "ros-jazzy-std-msgs",
    "std_srvs": "ros-jazzy-std-srvs",
    "diagnostic_msgs": "ros-jazzy-diagnostic-msgs",
    "python3-numpy": "numpy",
    "python3-scipy": "scipy",
    "python3-opencv": "opencv-python-headless",
    "python3-yaml": "PyYAML",
    "python3-tqdm": "tqdm",
    "python3-h5py": "h5py",
    "python3-torch": "torch",
    "python3-rosbags-pip": "rosbags",
}
# rosdep keys with no pip wheel: what `ros2 launch` needs for launch/neurncd.launch.py. A ROS
# install has them; without it bringup starts the nodes (test_packaging checks package.xml).
ROS_ONLY_DEPENDENCIES = ("launch", "launch_ros")

NODES = ("embedding", "mapper", "discovery", "replay", "bringup")

setup(
    name=PACKAGE,
    version=VERSION,
    packages=find_packages(exclude=["test", "test.*", "bench"]),
    package_data={PACKAGE: ["models/*.pt", "models/*.json"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    # ROS installs provide these through rosdep (package.xml); pip users get
    # them pinned from requirements.txt. Only setuptools is needed to build.
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="neurncd_ros developers",
    maintainer_email="neurncd@example.org",
    description="Online novel class discovery from RGB-D with an Embedding-NeRF (ROS 2).",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [f"{n} = {PACKAGE}.nodes.{n}:main" for n in NODES]
        + [f"neurncd = {PACKAGE}.cli:main"],
    },
)
