"""Detected objects for RViz and MoveIt: a mesh Marker at each pose, and a planning-scene CollisionObject.

`marker_array()` builds `visualization_msgs/MarkerArray`: a DELETEALL marker (so objects no longer seen
disappear), then one MESH_RESOURCE marker per detection, the object's textured `mesh.obj` named by a `file://`
URI with its embedded materials, at the detection's pose. RViz on the same machine shows it as is.

`collision_object_fields()` says what a `moveit_msgs/CollisionObject` of a detection holds, as plain values
(header frame, id, pose, one `shape_msgs/Mesh` in the object frame, operation); `collision_object()` fills the
message from them where `moveit_msgs` is installed. The first message of an object ADDs it with its mesh, later
ones MOVE it (pose only), as MoveIt's planning scene monitor takes them on `/collision_object`.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from types import ModuleType

import numpy as np
from geometry_msgs.msg import Point, Vector3
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from n2d_common.formats.model import read_model_mesh
from n2d_common.ros import pose_msg
from n2d_dope.infer import Detection

ADD, MOVE = 0, 3
"""moveit_msgs/CollisionObject operations."""
COLLISION_FACES = 2000
"""Most faces of a collision mesh: enough for grasp planning, cheap for collision checks."""


def mesh_uri(object_dir: Path) -> str:
    """The `file://` URI of a model directory's mesh, as Marker.mesh_resource names it."""
    return (Path(object_dir) / "mesh.obj").resolve().as_uri()


def marker_array(detections: list[Detection], header: Header, meshes: dict[str, str]) -> MarkerArray:
    """DELETEALL, then a mesh marker per detection whose object has a mesh in `meshes` (object name: URI);
    namespace the object's name, ids counting up per object."""
    markers = [Marker(header=header, action=Marker.DELETEALL)]
    count: dict[str, int] = {}
    for det in detections:
        if det.object not in meshes:
            continue
        count[det.object] = count.get(det.object, -1) + 1
        markers.append(Marker(header=header, ns=det.object, id=count[det.object], type=Marker.MESH_RESOURCE,
                              action=Marker.ADD, pose=pose_msg(det.T_cam_obj), scale=Vector3(x=1.0, y=1.0, z=1.0),
                              color=ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0), mesh_resource=meshes[det.object],
                              mesh_use_embedded_materials=True))
    return MarkerArray(markers=markers)


def collision_mesh(object_dir: Path, max_faces: int = COLLISION_FACES) -> tuple[np.ndarray, np.ndarray]:
    """(V x 3 vertices in metres, F x 3 faces) of a model's mesh in the object frame, decimated to `max_faces`."""
    mesh = read_model_mesh(Path(object_dir))
    vertices, faces = np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)
    if len(faces) > max_faces:
        import fast_simplification

        vertices, faces = fast_simplification.simplify(vertices.astype(np.float32), faces.astype(np.int32),
                                                       target_reduction=1.0 - max_faces / len(faces))
    return np.asarray(vertices, float), np.asarray(faces, np.int64)


def collision_object_fields(det: Detection, frame_id: str, object_id: str,
                            mesh: tuple[np.ndarray, np.ndarray] | None) -> dict:
    """What the CollisionObject of a detection holds: `header.frame_id` (the camera), `id`, `pose` (object frame
    in the camera frame, 4 x 4), `meshes` ([(vertices, faces)] in the object frame, with identity `mesh_poses`)
    and `operation`: ADD with the mesh when `mesh` is given, else MOVE (the pose of an object already added)."""
    return {"frame_id": frame_id, "id": object_id, "pose": det.T_cam_obj,
            "meshes": [] if mesh is None else [mesh], "operation": ADD if mesh is not None else MOVE}


def moveit_modules() -> tuple[ModuleType, ModuleType] | None:
    """(moveit_msgs.msg, shape_msgs.msg) where MoveIt's messages are installed, else None."""
    try:
        return importlib.import_module("moveit_msgs.msg"), importlib.import_module("shape_msgs.msg")
    except ImportError:
        return None


def collision_object(fields: dict, header: Header, modules: tuple[ModuleType, ModuleType]):
    """moveit_msgs/CollisionObject from `collision_object_fields()`."""
    moveit, shapes = modules
    identity = pose_msg(np.eye(4))
    meshes = [shapes.Mesh(vertices=[Point(x=float(x), y=float(y), z=float(z)) for x, y, z in vertices],
                          triangles=[shapes.MeshTriangle(vertex_indices=[int(i) for i in face]) for face in faces])
              for vertices, faces in fields["meshes"]]
    return moveit.CollisionObject(header=Header(stamp=header.stamp, frame_id=fields["frame_id"]), id=fields["id"],
                                  pose=pose_msg(fields["pose"]), meshes=meshes, mesh_poses=[identity] * len(meshes),
                                  operation=fields["operation"])
