"""Pose tracking over a video stream: detect once, then follow the object frame to frame by refinement.

For each frame the last pose, moved on by a constant-velocity motion model, starts a short region-based
refinement (`n2d_dope.pose_refine`) that also takes the texture points of the last frame, followed into this one
by optical flow (`n2d_dope.flow`): the object is tracked at the refinement's cost (a few milliseconds) instead
of the network's. The detector runs again while no object is tracked, and every `redetect_frames` frames while
one is; a detection that disagrees with the track replaces it only when it agrees better with the image
(silhouette and texture), so a track that slipped is corrected and a stray detection does not break a good one.
A track is lost when its silhouette score drops below `lost_score` (the object left the view, or is hidden), or
when the image's texture stops matching the model's albedo there (checked every `texture_frames` tracked frames:
a silhouette alone can hold on to a wrong pose against a busy background); a
gap between frames longer than `max_gap_s`, a frame older than the last one or new intrinsics restart the motion
model. Published poses are the refinement's own: no low-pass filter, so no lag.

Pure library, one object per `Tracker` (its best instance). `Tracker.step(rgb, K, stamp)` does everything in
the caller's thread (benchmarks, tests); dope_node calls `track` on every frame and runs `detect` in a worker of
its own, handing the result back with `offer`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from n2d_common.frames import make_T, transform_points
from n2d_dope.config import FlowConfig, RefineConfig
from n2d_dope.flow import FlowPoints
from n2d_dope.infer import Detection, DopeModel
from n2d_dope.pose_refine import pose_score, refine_pose, texture_agreement


def _track_refine() -> RefineConfig:
    return RefineConfig(scales=(4, 2, 1), iterations=2)


@dataclass
class TrackConfig:
    """Tracking an object through a stream."""

    redetect_frames: int = 10
    """While tracking, run the detector again every this many frames (0: only when the track is lost)."""
    lost_score: float = 0.6
    """A tracked pose whose silhouette score falls below this ends the track."""
    texture_frames: int = 3
    """Every this many tracked frames, the texture agreement of the pose is checked (0: never); below
    `refine.min_texture` (where the albedo can be compared) the track ends."""
    agree_fraction: float = 0.1
    """A detection within this fraction of the object's size (mean distance of the cuboid corners) of the track
    agrees with it."""
    replace_margin: float = 0.02
    """A disagreeing detection replaces the track when its silhouette + texture agreement is higher by this."""
    max_gap_s: float = 0.5
    """Frames further apart than this (seconds) restart the motion model."""
    velocity_gain: float = 0.7
    """Share of the last frame-to-frame motion the motion model carries into the next frame (1: constant velocity,
    0: none); below 1 it does not overshoot when the object stops."""
    refine: RefineConfig = field(default_factory=_track_refine)
    """The refinement run on every tracked frame (shorter than the one after a detection)."""
    flow: FlowConfig = field(default_factory=FlowConfig)
    """Texture points followed from frame to frame (`n2d_dope.flow`), a term of each tracked frame's refinement
    beside the silhouette (`flow.points` 0: silhouette only)."""

    def __post_init__(self):
        if self.redetect_frames < 0 or self.texture_frames < 0:
            raise ValueError(f"redetect_frames and texture_frames must be >= 0, got {self.redetect_frames} and "
                             f"{self.texture_frames}")
        if not 0.0 <= self.velocity_gain <= 1.0:
            raise ValueError(f"velocity_gain must be in 0..1, got {self.velocity_gain}")
        if self.max_gap_s <= 0 or self.agree_fraction <= 0:
            raise ValueError("max_gap_s and agree_fraction must be > 0")


@dataclass
class TrackedPose:
    """The pose of the tracked object in one frame."""

    object: str
    T_cam_obj: np.ndarray
    """4 x 4: object frame -> OpenCV camera frame, metres."""
    score: float
    """Silhouette score of the pose in this frame (`n2d_dope.pose_refine.pose_score`)."""
    source: str
    """"detected" (a detection started or replaced the track in this frame or, for `track`, since the last
    frame) or "tracked"."""
    stamp: float
    """Time of the frame, seconds."""


class Tracker:
    """Detect-then-track of one object; the DOPE model must refine its detections (`DopeModel(refine=...)`)."""

    def __init__(self, model: DopeModel, cfg: TrackConfig | None = None):
        if model.refiner is None:
            raise ValueError("Tracker needs a DopeModel that refines its detections (refine=RefineConfig())")
        self.model = model
        self.cfg = cfg or TrackConfig()
        self.size_m = float(np.linalg.norm(np.ptp(model.cuboid_m[:8], axis=0)))
        textured = model.refiner.textured
        self.flow = FlowPoints(textured.vertices, textured.faces, self.cfg.flow) if self.cfg.flow.points else None
        self.reset()

    def reset(self) -> None:
        """Forget the track (the next frame is detected)."""
        self.pose: TrackedPose | None = None
        self._omega = np.zeros(3)  # rotation rate about the object's centre, camera axes, rad/s
        self._velocity = np.zeros(3)  # m/s, camera axes
        self._K: np.ndarray | None = None
        self._size: tuple[int, int] | None = None
        self._since_detection = 0
        self._since_texture = 0
        self._adopted = False  # the pose is a detection not yet followed into a frame
        if self.flow is not None:
            self.flow.reset()

    @property
    def tracking(self) -> bool:
        return self.pose is not None

    def needs_detection(self) -> bool:
        """Whether the detector should run on the coming frame."""
        if self.pose is None:
            return True
        return self.cfg.redetect_frames > 0 and self._since_detection >= self.cfg.redetect_frames

    def _check_stream(self, rgb: np.ndarray, K: np.ndarray, stamp: float) -> None:
        """New intrinsics or image size: start over; a gap or a frame out of order: no motion to carry on."""
        size = rgb.shape[:2]
        if self._K is not None and (size != self._size or not np.allclose(K, self._K)):
            self.reset()
        self._K, self._size = np.array(K, float), size
        if self.pose is not None and not 0.0 < stamp - self.pose.stamp <= self.cfg.max_gap_s:
            self._omega[:] = 0.0
            self._velocity[:] = 0.0
            if self.flow is not None:
                self.flow.reset()  # flow follows consecutive frames only

    def predict(self, stamp: float) -> np.ndarray | None:
        """The tracked pose moved on to `stamp` by the motion model (None while not tracking)."""
        if self.pose is None:
            return None
        dt = max(0.0, stamp - self.pose.stamp)
        T = self.pose.T_cam_obj
        R = cv2.Rodrigues(self._omega * dt)[0] @ T[:3, :3]
        return make_T(R, T[:3, 3] + self._velocity * dt)

    def _update(self, T_new: np.ndarray, score: float, source: str, stamp: float) -> TrackedPose:
        if self.pose is not None and source == "tracked" and not self._adopted:
            dt = stamp - self.pose.stamp
            if dt > 0:
                T_old = self.pose.T_cam_obj
                rotvec = cv2.Rodrigues(T_new[:3, :3] @ T_old[:3, :3].T)[0][:, 0]
                self._omega = self.cfg.velocity_gain * rotvec / dt
                self._velocity = self.cfg.velocity_gain * (T_new[:3, 3] - T_old[:3, 3]) / dt
        else:
            self._omega[:] = 0.0
            self._velocity[:] = 0.0
        self._adopted = source == "detected"
        self.pose = TrackedPose(self.model.name, T_new, score, source, stamp)
        return self.pose

    def track(self, rgb: np.ndarray, K: np.ndarray, stamp: float) -> TrackedPose | None:
        """Follow the tracked object into a new frame (refinement only); None when there is no track or it was
        lost in this frame."""
        K = np.asarray(K, float)
        self._check_stream(rgb, K, stamp)
        predicted = self.predict(stamp)
        if predicted is None:
            return None
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if self.flow is not None else None
        points = self.flow.follow(gray) if self.flow is not None else None
        refined = refine_pose(rgb, K, predicted, self.model.refiner.region, self.cfg.refine, points,
                              self.cfg.flow.sigma_px)
        self._since_detection += 1
        if refined.score < self.cfg.lost_score or not self._texture_holds(rgb, K, refined.T_cam_obj):
            self.reset()
            return None
        if self.flow is not None:
            self.flow.select(gray, K, refined.T_cam_obj)
        first = self._adopted  # the first frame after a detection started or replaced the track
        pose = self._update(refined.T_cam_obj, refined.score, "tracked", stamp)
        if first:
            pose.source = "detected"
        return pose

    def _texture_holds(self, rgb: np.ndarray, K: np.ndarray, T: np.ndarray) -> bool:
        """False when a due texture check finds the image's texture does not match the model's at pose T."""
        if self.cfg.texture_frames == 0:
            return True
        self._since_texture += 1
        if self._since_texture < self.cfg.texture_frames:
            return True
        self._since_texture = 0
        texture = texture_agreement(rgb, K, T, self.model.refiner.textured)
        return not (np.isfinite(texture) and texture < self.cfg.refine.min_texture)

    def _fit(self, rgb: np.ndarray, K: np.ndarray, T: np.ndarray) -> float:
        """Silhouette score plus texture agreement (where the texture can be compared) of a pose in a frame."""
        refiner = self.model.refiner
        score = pose_score(rgb, K, T, refiner.region, refiner.cfg)[0]
        texture = texture_agreement(rgb, K, T, refiner.textured)
        return score + (texture if np.isfinite(texture) else 0.0)

    def offer(self, rgb: np.ndarray, K: np.ndarray, detections: list[Detection], stamp: float) -> TrackedPose | None:
        """Hand the tracker the detections of the frame (`rgb`, `K`) taken at `stamp`: the best starts a track
        when there is none, and replaces a disagreeing track when it agrees better with that frame. Returns the
        pose the track now has (None without track)."""
        K = np.asarray(K, float)
        ours = [d for d in detections if d.object == self.model.name]
        self._since_detection = 0
        if not ours:
            return self.pose
        best = max(ours, key=lambda d: (d.refine_score if np.isfinite(d.refine_score) else d.score))
        if self.pose is None:
            self._check_stream(rgb, K, stamp)
            return self._update(best.T_cam_obj, float(best.refine_score), "detected", stamp)
        corners = self.model.cuboid_m[:8]
        current = self.predict(stamp)
        apart = np.linalg.norm(transform_points(current, corners) - transform_points(best.T_cam_obj, corners),
                               axis=1).mean()
        if apart <= self.cfg.agree_fraction * self.size_m:
            return self.pose
        if self._fit(rgb, K, best.T_cam_obj) > self._fit(rgb, K, current) + self.cfg.replace_margin:
            if self.flow is not None:
                self.flow.reset()  # the points belong to the replaced pose (and maybe to a later frame)
            return self._update(best.T_cam_obj, float(best.refine_score), "detected", max(stamp, self.pose.stamp))
        return self.pose

    def step(self, rgb: np.ndarray, K: np.ndarray, stamp: float) -> TrackedPose | None:
        """Track, and detect when due, on one frame in the caller's thread."""
        tracked = self.track(rgb, K, stamp)
        if not self.needs_detection():
            return tracked
        return self.offer(rgb, K, self.model.detect(rgb, K), stamp)
