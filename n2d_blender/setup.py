"""ament_python / pip setup of n2d_blender."""
from setuptools import find_packages, setup

package_name = "n2d_blender"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(include=[package_name, package_name + ".*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="n2d developers",
    maintainer_email="n2d@example.org",
    description="n2d's small bpy layer (objects, materials, lighting, camera, physics, Cycles renderer)",
    license="Apache-2.0",
)
