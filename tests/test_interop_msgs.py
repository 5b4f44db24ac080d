"""The vision_msgs, visualization_msgs and tf2_msgs types n2d publishes are the upstream ones: their type hashes
(REP 2011), computed by rosidl from the upstream packages' definitions written out here, equal the hashes of the
installed packages."""

import json
import sys
from pathlib import Path

import pytest

UPSTREAM = {
    # ros-perception/vision_msgs 4.1.1, vision_msgs/msg (comments left out: they do not enter the hash)
    "vision_msgs": {
        "ObjectHypothesis": "string class_id\nfloat64 score\n",
        "ObjectHypothesisWithPose": "ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n",
        "BoundingBox3D": "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n",
        "Detection3D": "std_msgs/Header header\nObjectHypothesisWithPose[] results\nBoundingBox3D bbox\nstring id\n",
        "Detection3DArray": "std_msgs/Header header\nDetection3D[] detections\n",
    },
    # ros2/common_interfaces (Jazzy), visualization_msgs/msg: the Marker messages
    "visualization_msgs": {
        "UVCoordinate": "float32 u\nfloat32 v\n",
        "MeshFile": "string filename\nuint8[] data\n",
        "Marker": "".join(f"int32 {name}={value}\n" for value, name in enumerate(
            "ARROW CUBE SPHERE CYLINDER LINE_STRIP LINE_LIST CUBE_LIST SPHERE_LIST POINTS TEXT_VIEW_FACING "
            "MESH_RESOURCE TRIANGLE_LIST ARROW_STRIP".split()))
        + "int32 ADD=0\nint32 MODIFY=0\nint32 DELETE=2\nint32 DELETEALL=3\n"
        + "std_msgs/Header header\nstring ns\nint32 id\nint32 type\nint32 action\ngeometry_msgs/Pose pose\n"
        + "geometry_msgs/Vector3 scale\nstd_msgs/ColorRGBA color\nbuiltin_interfaces/Duration lifetime\n"
        + "bool frame_locked\ngeometry_msgs/Point[] points\nstd_msgs/ColorRGBA[] colors\nstring texture_resource\n"
        + "sensor_msgs/CompressedImage texture\nUVCoordinate[] uv_coordinates\nstring text\nstring mesh_resource\n"
        + "MeshFile mesh_file\nbool mesh_use_embedded_materials\n",
        "MarkerArray": "Marker[] markers\n",
    },
    # ros2/geometry2 (Jazzy), tf2_msgs/msg
    "tf2_msgs": {"TFMessage": "geometry_msgs/TransformStamped[] transforms\n"},
}
DEPENDENCIES = ("std_msgs", "geometry_msgs", "builtin_interfaces", "sensor_msgs")


def upstream_hashes(tmp_path: Path, package: str) -> dict[str, str]:
    """RIHS01 hash of each upstream message, by rosidl's own adapter and type-description generator."""
    from rosidl_adapter.msg import convert_msg_to_idl
    from rosidl_generator_type_description import generate_type_hash

    root = tmp_path / package
    (root / "msg").mkdir(parents=True)
    idl_dir, out = tmp_path / "idl", tmp_path / "out"
    for name, text in UPSTREAM[package].items():
        (root / "msg" / f"{name}.msg").write_text(text)
        convert_msg_to_idl(root, package, Path("msg") / f"{name}.msg", idl_dir / package / "msg")
    share = Path(sys.prefix) / "share"
    arguments = {"package_name": package, "output_dir": str(out),
                 "idl_tuples": [f"{idl_dir / package}:msg/{name}.idl" for name in UPSTREAM[package]],
                 "include_paths": [f"{d}:{share / d}" for d in DEPENDENCIES]}
    (tmp_path / "args.json").write_text(json.dumps(arguments))
    generate_type_hash(str(tmp_path / "args.json"))
    return {name: json.loads((out / "msg" / f"{name}.json").read_text())["type_hashes"][0]["hash_string"]
            for name in UPSTREAM[package]}


@pytest.mark.parametrize("package", sorted(UPSTREAM))
def test_installed_types_hash_as_upstream(tmp_path, package):
    expected = upstream_hashes(tmp_path, package)
    __import__(f"{package}.msg")  # importable: the Python side of the installed package
    share = Path(sys.prefix) / "share" / package / "msg"
    for name, hash_string in expected.items():
        installed = json.loads((share / f"{name}.json").read_text())["type_hashes"][0]
        assert installed["type_name"] == f"{package}/msg/{name}"
        assert installed["hash_string"] == hash_string, name
