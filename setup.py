"""ament_python build of vlocnetpp_ros: the ROS node package plus the ROS-free core library."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "vlocnetpp_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=["vlocnetpp_core", "vlocnetpp_core.*", "vlocnetpp_ros", "vlocnetpp_ros.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", sorted(glob("config/*.yaml") + glob("config/*.xml"))),
        (
            f"share/{PACKAGE}/models",
            sorted(glob("models/*.safetensors") + glob("models/*.json") + glob("models/*.npz")),
        ),
    ],
    install_requires=["setuptools"],
    extras_require={"onnx": ["onnx", "onnxruntime"]},  # backend: onnx, export-onnx (versions: requirements.txt)
    zip_safe=False,
    maintainer="VLocNet++ ROS maintainers",
    maintainer_email="maintainers@example.org",
    description="VLocNet++ global pose, visual odometry and semantic segmentation for ROS 2 Jazzy.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "localizer = vlocnetpp_ros.node:main",
            "vlocnetpp = vlocnetpp_core.cli:main",
            "vlocnetpp-replay-node = vlocnetpp_ros.replay_bridge:main",
            "vlocnetpp-latency-bench = vlocnetpp_ros.latency_bench:main",
            "vlocnetpp-soak = vlocnetpp_ros.soak:main",
        ],
        # the ROS programs the core starts by name (vlocnetpp_core/programs.py)
        "vlocnetpp.programs": [
            "replay-node = vlocnetpp_ros.replay_bridge:main",
            "latency-bench = vlocnetpp_ros.latency_bench:main",
            "soak = vlocnetpp_ros.soak:main",
        ],
    },
)
