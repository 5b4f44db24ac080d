"""ament_python / pip setup of n2d_dope."""
from setuptools import find_packages, setup

package_name = "n2d_dope"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(include=[package_name, package_name + ".*"]),
    include_package_data=True,
    package_data={package_name: ["**/*.yaml", "**/*.json", "**/*.obj", "**/*.mtl", "**/*.png", "**/*.pt"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="n2d developers",
    maintainer_email="n2d@example.org",
    description="DOPE stage of n2d",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "dope_node = n2d_dope.nodes.dope_node:main",
            "train_node = n2d_dope.nodes.train_node:main",
        ],
    },
)
