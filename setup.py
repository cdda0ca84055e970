"""ament_python build of saml_ros (``colcon build``); see docs/packaging.md.

ROS 2 dependencies come from apt / rosdep (package.xml) and the pip-only ones (torch, mujoco, rosbags)
from requirements.txt, so ``install_requires`` lists only setuptools, as ``ros2 pkg create`` does:
pip-resolving rclpy or torch here would fight the ROS installation.
"""

import ast
from pathlib import Path

from setuptools import find_packages, setup

package_name = "saml_ros"
here = Path(__file__).resolve().parent


def read_executables() -> dict[str, str]:
    """``EXECUTABLES`` from saml_ros/executables.py, parsed without importing saml_ros (no torch at build)."""
    tree = ast.parse((here / "saml_ros" / "executables.py").read_text())
    for node in tree.body:
        target = node.target if isinstance(node, ast.AnnAssign) else None
        if isinstance(node, ast.Assign) and len(node.targets) == 1:
            target = node.targets[0]
        if isinstance(target, ast.Name) and target.id == "EXECUTABLES" and node.value is not None:
            return dict(ast.literal_eval(node.value))
    raise RuntimeError("saml_ros/executables.py defines no EXECUTABLES dict")


setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(
        include=["saml_ros", "saml_ros.*", "sim_nodes", "sim_nodes.*", "msg_schemas", "msg_schemas.*"]
    ),
    package_data={"saml_ros.systems.paddle_ball": ["assets/*.xml"],
                  # the fused training kernel's source, compiled on first use (saml_ros/core/training/engines/fused.py)
                  "saml_ros.core.training.engines": ["kernels/*.cpp"],
                  # the fast SQP's C kernel, compiled on first use (saml_ros/core/mpc/shooting/native.py)
                  "saml_ros.core.mpc.shooting": ["kernels/*.c"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", sorted(str(p.relative_to(here)) for p in here.glob("config/*.yaml"))),
        ("share/" + package_name + "/launch", sorted(str(p.relative_to(here)) for p in here.glob("launch/*.launch.*"))),
        ("share/" + package_name + "/layouts", sorted(str(p.relative_to(here)) for p in here.glob("layouts/*.*"))),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="saml_ros maintainers",
    maintainer_email="saml_ros@example.org",
    description="Online Sufficiently Accurate Model Learning for ROS 2",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        # every script runs saml_ros.executables:entry, which dispatches on the script's name to the table's target
        # (and keeps a stop signal during start-up quiet)
        "console_scripts": [f"{name} = saml_ros.executables:entry" for name in read_executables()],
    },
)
