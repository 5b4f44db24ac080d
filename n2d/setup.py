"""ament_python / pip setup of n2d."""
from glob import glob

from setuptools import find_packages, setup

package_name = "n2d"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(include=[package_name, package_name + ".*"]),
    include_package_data=True,
    package_data={package_name: ["**/*.yaml", "**/*.json", "**/*.obj", "**/*.mtl", "**/*.png"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py") + glob("launch/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="n2d developers",
    maintainer_email="n2d@example.org",
    description="n2d bringup",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "n2d = n2d.cli:main",
            "pipeline_node = n2d.nodes.pipeline_node:main",
        ],
    },
)
