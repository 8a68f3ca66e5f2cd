"""Object detections from a depth image and a segmentation mask: pinhole geometry in numpy. Pure logic."""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping
from dataclasses import dataclass

import numpy as np
from shapely.geometry import MultiPoint

# An outline narrower than this (metres) is an edge, not a top: it tells no heading.
MIN_OUTLINE = 0.005


@dataclass(frozen=True)
class Intrinsics:
    """A pinhole camera in OpenGL conventions: square pixels, depth clipped to [near, far] metres."""

    width: int
    height: int
    hfov: float  # radians
    near: float
    far: float

    @property
    def tan_half_h(self) -> float:
        return math.tan(self.hfov / 2)

    @property
    def tan_half_v(self) -> float:
        return self.tan_half_h * self.height / self.width

    def projection_matrix(self) -> list[float]:
        """The OpenGL projection, column-major as pybullet takes it."""
        near, far = self.near, self.far
        projection = np.array(
            [
                [1 / self.tan_half_h, 0.0, 0.0, 0.0],
                [0.0, 1 / self.tan_half_v, 0.0, 0.0],
                [0.0, 0.0, (far + near) / (near - far), 2 * far * near / (near - far)],
                [0.0, 0.0, -1.0, 0.0],
            ]
        )
        return projection.T.ravel().tolist()


@dataclass(frozen=True)
class Target:
    """A body worth reporting: its name, its height (the world file knows how tall things are) and,
    for one whose footprint is not round, its footprint's sides (x, y), so its heading can be told."""

    name: str
    height: float
    footprint: tuple[float, float] | None = None


@dataclass(frozen=True)
class Detection:
    """Where a body is (map-frame centre) and, when its footprint is not round, its heading: the
    direction of its footprint's x side, modulo a half turn, in (-pi/2, pi/2]."""

    centre: np.ndarray
    yaw: float | None = None


def camera_pose(x: float, y: float, yaw: float, mount_x: float, mount_z: float, pitch: float) -> np.ndarray:
    """Camera-to-map transform (4x4) of a camera `mount_x` ahead of a base at (x, y, yaw) and
    `mount_z` above the floor, looking ahead and `pitch` radians down. OpenGL camera axes: x right,
    y up, looking along -z."""
    forward = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), -math.sin(pitch)])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    up = np.cross(right, forward)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = right, up, -forward
    pose[:3, 3] = (x + mount_x * math.cos(yaw), y + mount_x * math.sin(yaw), mount_z)
    return pose


def view_matrix(pose: np.ndarray) -> list[float]:
    """The OpenGL view matrix (map to camera) of a camera pose, column-major as pybullet takes it."""
    return np.linalg.inv(pose).T.ravel().tolist()


def linear_depth(buffer: np.ndarray, near: float, far: float) -> np.ndarray:
    """Metres along the optical axis from OpenGL depth-buffer values in [0, 1]."""
    return far * near / (far - (far - near) * buffer)


def unproject(
    rows: np.ndarray, cols: np.ndarray, depth: np.ndarray, camera: Intrinsics, pose: np.ndarray
) -> np.ndarray:
    """Map-frame points (n x 3) of the pixels at (rows, cols) whose depths along the axis are `depth`.

    Rows count from the top of the image. Each pixel is sampled at its lower-left corner in window
    coordinates (origin bottom-left), as pybullet's renderer does; at pixel centres every point
    would be half a pixel (several millimetres) off.
    """
    x_ndc = 2.0 * cols / camera.width - 1.0
    y_ndc = 2.0 * (camera.height - 1 - rows) / camera.height - 1.0
    in_camera = np.stack(
        [x_ndc * camera.tan_half_h * depth, y_ndc * camera.tan_half_v * depth, -depth, np.ones_like(depth)]
    )
    return (pose @ in_camera)[:3].T


def estimate_centre(points: np.ndarray, height: float) -> np.ndarray:
    """The centre of an object `height` tall from the map-frame points of its visible surface.

    Their mean would sit on the surface, up to a radius towards the camera. Seen from above, the
    top and the near side together span the whole footprint, so the middle of their xy extent is
    the middle of the object; its highest point is its top. (The rendered depth is exact, so the
    extremes need no trimming; the noise goes on the estimate.)
    """
    low, high = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    return np.array([(low[0] + high[0]) / 2, (low[1] + high[1]) / 2, points[:, 2].max() - height / 2])


def estimate_yaw(points: np.ndarray, footprint: tuple[float, float]) -> float | None:
    """The heading of an object whose footprint has sides `footprint` (x, y), from the map-frame
    points of its visible surface: the smallest rectangle around them seen from above has the
    object's sides; the one closer in length to the x side gives the heading. None when the points
    span no area (seen edge on)."""
    outline = MultiPoint(points[:, :2].tolist()).minimum_rotated_rectangle
    corners = np.asarray(getattr(outline, "exterior", outline).coords)
    if len(corners) < 4:
        return None
    edges = [corners[1] - corners[0], corners[2] - corners[1]]
    lengths = [float(np.hypot(*e)) for e in edges]
    if min(lengths) < MIN_OUTLINE:
        return None
    side = min(range(2), key=lambda k: abs(lengths[k] - footprint[0]))
    yaw = math.atan2(edges[side][1], edges[side][0])
    # A rectangle looks the same turned half round: keep the heading in (-pi/2, pi/2].
    return yaw - math.pi if yaw > math.pi / 2 else yaw + math.pi if yaw <= -math.pi / 2 else yaw


def detect(
    segmentation: np.ndarray,
    depth_buffer: np.ndarray,
    camera: Intrinsics,
    pose: np.ndarray,
    bodies: Mapping[int, Target],
    *,
    min_pixels: int,
    max_range: float,
    occluders: Collection[int] = (),
) -> dict[str, Detection]:
    """The estimated centres (map frame), and headings where they tell, of the bodies in `bodies`
    (segmentation id -> target) seen in the image, by name.

    A body counts when at least `min_pixels` of its pixels lie within `max_range` metres along the
    optical axis (beyond that the sensor returns nothing), none of them touches the image border and
    none borders a nearer pixel of one of `occluders` (the robot): half an object would put its
    centre half a size off, and so would the end of one the robot's hand above it hides.
    """
    ids = np.fromiter(bodies, dtype=segmentation.dtype, count=len(bodies))
    hidden = _beside_nearer(segmentation, depth_buffer, occluders)
    rows, cols = np.nonzero(np.isin(segmentation, ids))
    depth = linear_depth(depth_buffer[rows, cols], camera.near, camera.far)
    in_range = depth <= max_range
    rows, cols, depth = rows[in_range], cols[in_range], depth[in_range]
    labels = segmentation[rows, cols]
    found: dict[str, Detection] = {}
    for body in np.unique(labels):
        mine = labels == body
        if (
            np.count_nonzero(mine) < min_pixels
            or _touches_border(rows[mine], cols[mine], camera)
            or hidden[rows[mine], cols[mine]].any()
        ):
            continue
        points = unproject(rows[mine], cols[mine], depth[mine], camera, pose)
        target = bodies[int(body)]
        yaw = estimate_yaw(points, target.footprint) if target.footprint is not None else None
        found[target.name] = Detection(estimate_centre(points, target.height), yaw)
    return found


def _touches_border(rows: np.ndarray, cols: np.ndarray, camera: Intrinsics) -> bool:
    return bool(rows.min() == 0 or cols.min() == 0 or rows.max() == camera.height - 1 or cols.max() == camera.width - 1)


def _beside_nearer(segmentation: np.ndarray, depth_buffer: np.ndarray, occluders: Collection[int]) -> np.ndarray:
    """Which pixels have a neighbour (above, below, left or right) of one of `occluders` nearer the
    camera: where one of those hides what lies beyond. (Depth-buffer values grow with distance.)"""
    near = np.where(np.isin(segmentation, list(occluders)), depth_buffer, np.inf)
    hidden = np.zeros(segmentation.shape, dtype=bool)
    hidden[1:, :] |= near[:-1, :] < depth_buffer[1:, :]
    hidden[:-1, :] |= near[1:, :] < depth_buffer[:-1, :]
    hidden[:, 1:] |= near[:, :-1] < depth_buffer[:, 1:]
    hidden[:, :-1] |= near[:, 1:] < depth_buffer[:, :-1]
    return hidden
