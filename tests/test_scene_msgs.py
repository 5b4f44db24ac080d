"""RViz markers and MoveIt collision objects of detections: built on hand-made detections of the sample box."""

from types import SimpleNamespace

import numpy as np
import trimesh
from std_msgs.msg import Header
from visualization_msgs.msg import Marker

from n2d_common.formats.model import read_model_mesh
from n2d_common.frames import make_T, rot_z
from n2d_common.ros import stamp_msg
from n2d_dope.infer import Detection
from n2d_dope.nodes.scene_msgs import (
    ADD,
    MOVE,
    collision_mesh,
    collision_object,
    collision_object_fields,
    marker_array,
    mesh_uri,
)
from n2d_sim.objects import sample_object_dir

T = make_T(rot_z(0.3)[:3, :3], [0.05, -0.02, 0.6])
HEADER = Header(stamp=stamp_msg(3.25), frame_id="cam")


def _det(name: str) -> Detection:
    return Detection(name, T, 0.9, np.zeros((9, 2)), 1.0)


def test_marker_array_clears_then_draws_each_object_with_its_mesh():
    box = sample_object_dir("box")
    markers = marker_array([_det("box"), _det("box"), _det("mug")], HEADER, {"box": mesh_uri(box)}).markers
    assert markers[0].action == Marker.DELETEALL
    assert [(m.ns, m.id) for m in markers[1:]] == [("box", 0), ("box", 1)]  # no mesh, no marker: the mug
    m = markers[1]
    assert m.type == Marker.MESH_RESOURCE and m.mesh_use_embedded_materials and m.header.frame_id == "cam"
    assert m.mesh_resource.startswith("file:///") and m.mesh_resource.endswith("/box/mesh.obj")
    assert (m.scale.x, m.scale.y, m.scale.z, m.color.a) == (1.0, 1.0, 1.0, 1.0)
    assert np.allclose([m.pose.position.x, m.pose.position.y, m.pose.position.z], T[:3, 3])


def test_collision_mesh_keeps_the_shape_within_the_face_budget():
    box = sample_object_dir("box")
    full = read_model_mesh(box)
    vertices, faces = collision_mesh(box, max_faces=200)
    assert len(faces) <= 200 < len(full.faces)
    coarse = trimesh.Trimesh(vertices, faces)
    assert np.allclose(coarse.bounds, full.bounds, atol=0.004)  # metres, object frame: the box keeps its size


def test_collision_object_is_added_once_with_its_mesh_then_moved():
    mesh = (np.eye(3), np.array([[0, 1, 2]]))
    added = collision_object_fields(_det("box"), "cam", "n2d/box", mesh)
    moved = collision_object_fields(_det("box"), "cam", "n2d/box", None)
    assert (added["operation"], len(added["meshes"]), moved["operation"], moved["meshes"]) == (ADD, 1, MOVE, [])
    assert added["frame_id"] == "cam" and np.array_equal(added["pose"], T)

    # A stand-in for moveit_msgs/shape_msgs (not installable here): message classes that keep their fields.
    def message(**fields):
        return SimpleNamespace(**fields)

    stand_in = (SimpleNamespace(CollisionObject=message), SimpleNamespace(Mesh=message, MeshTriangle=message))
    msg = collision_object(added, HEADER, stand_in)
    assert msg.id == "n2d/box" and msg.operation == ADD and msg.header.frame_id == "cam"
    assert [(p.x, p.y, p.z) for p in msg.meshes[0].vertices] == [(1, 0, 0), (0, 1, 0), (0, 0, 1)]
    assert list(msg.meshes[0].triangles[0].vertex_indices) == [0, 1, 2]
    assert len(msg.mesh_poses) == 1 and msg.mesh_poses[0].orientation.w == 1.0
    assert np.isclose(msg.pose.position.z, 0.6)
