"""Scoring on a BOP-format split with known answers: a hand-made split (two scenes, a second object to skip, a
BOP19 targets file), scored with a stand-in detector that returns the truth, or the truth shifted by 10 mm:
100 % everywhere, and the ADD, MSSD recall and CSV such a shift must give; bad input refused."""

import json

import cv2
import numpy as np
import pytest
import trimesh

from n2d_common.errors import ContractError
from n2d_common.frames import make_T
from n2d_dope.bop_eval import CSV_COLUMNS, read_csv, read_split, score_bop
from n2d_dope.infer import Detection, Timing

BOX_MM = (90.0, 60.0, 140.0)
K = [600.0, 0.0, 319.5, 0.0, 600.0, 239.5, 0.0, 0.0, 1.0]


def _pose(angle: float, z: float) -> np.ndarray:
    return make_T(cv2.Rodrigues(np.array([0.3, angle, 0.1]))[0], [0.02, -0.01, z])


@pytest.fixture
def bop(tmp_path):
    """models/ (obj 1: a 90 x 60 x 140 mm box; obj 2: a cube) and test/ with scenes 1 and 2."""
    (tmp_path / "models").mkdir()
    trimesh.creation.box(extents=BOX_MM).export(tmp_path / "models" / "obj_000001.ply")
    trimesh.creation.box(extents=(50, 50, 50)).export(tmp_path / "models" / "obj_000002.ply")
    info = {"1": {"diameter": float(np.linalg.norm(BOX_MM)), "symmetries_discrete": []},
            "2": {"diameter": 86.6}}
    (tmp_path / "models" / "models_info.json").write_text(json.dumps(info))
    truths = {}
    for scene_id in (1, 2):
        scene = tmp_path / "test" / f"{scene_id:06d}"
        (scene / "rgb").mkdir(parents=True)
        gt, cam, gt_info = {}, {}, {}
        for im_id in range(2):
            T = _pose(0.4 * im_id + scene_id, 0.5 + 0.1 * im_id)
            truths[(scene_id, im_id)] = T
            gt[str(im_id)] = [{"obj_id": 2, "cam_R_m2c": np.eye(3).ravel().tolist(), "cam_t_m2c": [0, 0, 900.0]},
                              {"obj_id": 1, "cam_R_m2c": T[:3, :3].ravel().tolist(),
                               "cam_t_m2c": (1000 * T[:3, 3]).tolist()}]
            cam[str(im_id)] = {"cam_K": K, "depth_scale": 1.0}
            gt_info[str(im_id)] = [{"visib_fract": 1.0}, {"visib_fract": 0.2 + 0.5 * im_id}]
            cv2.imwrite(str(scene / "rgb" / f"{im_id:06d}.png"), np.zeros((480, 640, 3), np.uint8))
        for name, data in (("scene_gt", gt), ("scene_camera", cam), ("scene_gt_info", gt_info)):
            (scene / f"{name}.json").write_text(json.dumps(data))
    return tmp_path, truths


class Oracle:
    """Stand-in detector: the truth of the image it is given (in read order), moved by `shift` (4 x 4, in the
    camera frame)."""

    precision, refiner, name = "fp32", None, "box"

    def __init__(self, truths: list[np.ndarray], shift: np.ndarray):
        self.truths, self.shift, self.timing = iter(truths), shift, Timing()
        lo, hi = -np.array(BOX_MM) / 2000, np.array(BOX_MM) / 2000
        corners = [[x, y, z] for x in (hi[0], lo[0]) for y in (hi[1], lo[1]) for z in (hi[2], lo[2])]
        self.cuboid_m = np.vstack([corners, np.zeros(3)])

    def detect(self, rgb, K):
        return [Detection("box", self.shift @ next(self.truths), 0.9, np.full((9, 2), np.nan), 0.0)]


def test_reads_the_split_and_the_targets(bop, tmp_path):
    root, truths = bop
    images = list(read_split(root, 1))
    assert [(im.scene_id, im.im_id) for im in images] == [(1, 0), (1, 1), (2, 0), (2, 1)]
    assert all(len(im.truths) == 1 and np.allclose(im.truths[0], truths[(im.scene_id, im.im_id)]) for im in images)
    assert [im.visible for im in images][:2] == [[0.2], [0.7]]
    targets = tmp_path / "targets.json"
    targets.write_text(json.dumps([{"scene_id": 2, "im_id": 1, "obj_id": 1, "inst_count": 1},
                                   {"scene_id": 1, "im_id": 0, "obj_id": 2, "inst_count": 1}]))
    assert [(im.scene_id, im.im_id) for im in read_split(root, 1, targets=targets)] == [(2, 1)]


def test_exact_poses_score_everything_and_the_csv_round_trips(bop, tmp_path):
    root, truths = bop
    order = [truths[k] for k in sorted(truths)]
    result, _ = score_bop(Oracle(order, np.eye(4)), root, 1, csv_path=tmp_path / "out.csv")
    assert result["instances"] == result["detected"] == 4
    assert result["add_accuracy_10pct"] == result["adds_accuracy_10pct"] == 1.0
    assert result["mssd_recall"] == result["mspd_recall"] == 1.0
    assert result["visibility_buckets"]["0.1-0.3"]["instances"] == 2
    rows = read_csv(tmp_path / "out.csv")
    assert tuple(rows[0]) == CSV_COLUMNS and len(rows) == 4
    assert [(int(r["scene_id"]), int(r["im_id"]), int(r["obj_id"])) for r in rows][1] == (1, 1, 1)
    for r, T in zip(rows, order):
        assert np.allclose(r["R"], T[:3, :3], atol=1e-7) and np.allclose(r["t"], T[:3, 3], atol=1e-6)


def test_a_10_mm_shift_gives_the_add_it_must(bop):
    root, truths = bop
    shift = make_T(np.eye(3), [0.010, 0.0, 0.0])
    result, _ = score_bop(Oracle([truths[k] for k in sorted(truths)], shift), root, 1)
    assert result["add_median_mm"] == pytest.approx(10.0, abs=1e-6)  # every point moves 10 mm
    assert result["add_accuracy_10pct"] == 1.0  # 10 mm < 10 % of the 177 mm diameter
    # MSSD is 10 mm too: below 9 of BOP's 10 thresholds (5 % .. 50 % of the diameter; 5 % is 8.8 mm)
    assert result["mssd_recall"] == pytest.approx(0.9)


def test_bad_input(bop):
    root, truths = bop
    detector = Oracle([truths[k] for k in sorted(truths)], np.eye(4))
    with pytest.raises(ContractError, match="no object 7"):
        score_bop(detector, root, 7)
    with pytest.raises(ContractError, match="no split 'val'"):
        score_bop(detector, root, 1, split="val")
    gt_path = root / "test" / "000001" / "scene_gt.json"
    gt = json.loads(gt_path.read_text())
    gt["1"][1]["cam_t_m2c"] = [0.0, float("nan"), 500.0]
    gt_path.write_text(json.dumps(gt))
    with pytest.raises(ContractError, match="image 1 has a malformed"):
        list(read_split(root, 1))
    del gt["1"][1]["cam_R_m2c"]
    gt_path.write_text(json.dumps(gt))
    with pytest.raises(ContractError, match="cam_R_m2c"):
        list(read_split(root, 1))
    gt_path.write_text("{not json")
    with pytest.raises(ContractError, match="not valid JSON"):
        list(read_split(root, 1))
    info_path = root / "models" / "models_info.json"
    info_path.write_text(json.dumps({"1": {"diameter": "big"}}))
    with pytest.raises(ContractError, match="numeric diameter"):
        score_bop(detector, root, 1)
