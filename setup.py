"""packml_ros2: PackML (ISA-TR88.00.02) units, equipment modules and cells on ROS 2."""

from glob import glob

from setuptools import find_packages, setup

package_name = "packml_ros2"

setup(
    name=package_name,
    version="0.1.0",
    description=__doc__,
    license="Apache-2.0",
    python_requires=">=3.10",
    packages=find_packages(include=[package_name, f"{package_name}.*"]),
    package_data={package_name: ["py.typed", "hmi/static/*", "hmi/static/**/*", "opcua/nodeset/*"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{package_name}"]),
        (f"share/{package_name}", ["package.xml"]),
        (f"share/{package_name}/config", glob("config/*.yaml") + glob("config/*.xml")),
        (f"share/{package_name}/launch", glob("launch/*.py")),
    ],
    install_requires=[
        "setuptools",
        "PyYAML>=6",
        "rosbags>=0.10",
        "fastapi>=0.110",  # packml hmi
        "uvicorn>=0.30",
        "asyncua>=1.1",  # packml opcua
        "paho-mqtt>=1.6,<2",  # packml mqtt
        "cryptography",
    ],
    # what only the tests use besides the dev tools: the MQTT tests' independent Sparkplug decoder
    extras_require={"test": ["pysparkplug>=0.6"]},
    zip_safe=False,
    entry_points={
        "console_scripts": [
            "packml = packml_ros2.cli.main:main",
            "unit_node = packml_ros2.unit_node:main",
            "plc_bridge = packml_ros2.plc.node:main",
            "em_node = packml_ros2.sim_em:main",
            "interface_em = packml_ros2.interface_em:main",
            "coordinator = packml_ros2.coordinator_node:main",
            "pick_and_place = packml_ros2.examples.pick_and_place:main",
        ],
        "pytest11": ["packml_ros2 = packml_ros2.testing.plugin"],
    },
)
