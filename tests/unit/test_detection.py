"""Detection from depth and segmentation, pure numpy: synthetic images of known boxes in, known centres out."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.sim.detection import (
    Intrinsics,
    Target,
    camera_pose,
    detect,
    estimate_centre,
    estimate_yaw,
    linear_depth,
    unproject,
    view_matrix,
)

CAMERA = Intrinsics(width=160, height=120, hfov=math.radians(87.0), near=0.1, far=4.0)
# A base at the origin facing +x; the camera 1.35 m up at its front edge, looking 45 degrees down.
POSE = camera_pose(0.0, 0.0, 0.0, 0.3, 1.35, math.radians(45.0))
FLOOR = 1


def column_major(values: list[float]) -> np.ndarray:
    return np.array(values).reshape(4, 4).T


def map_to_clip(camera: Intrinsics, pose: np.ndarray) -> np.ndarray:
    """Projection times view: the OpenGL matrices pybullet is given, as one 4x4."""
    return column_major(camera.projection_matrix()) @ column_major(view_matrix(pose))


def project(points: np.ndarray, camera: Intrinsics, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The window position (row from the top, column) and depth-buffer value of each map-frame point."""
    clip = map_to_clip(camera, pose) @ np.c_[points, np.ones(len(points))].T
    ndc = clip[:3] / clip[3]
    cols = (ndc[0] + 1) / 2 * camera.width
    rows = camera.height - 1 - (ndc[1] + 1) / 2 * camera.height
    return rows, cols, (ndc[2] + 1) / 2


Box = tuple[int, tuple[float, float, float], tuple[float, float, float]]  # id, centre, size


def render(boxes: list[Box], camera: Intrinsics = CAMERA, pose: np.ndarray = POSE) -> tuple[np.ndarray, np.ndarray]:
    """A ray-cast segmentation mask and depth buffer of axis-aligned boxes on a floor (id FLOOR)."""
    rows, cols = np.mgrid[0 : camera.height, 0 : camera.width]
    # Each pixel's ray, from the inverse of the same matrices: window corner -> points on near and far planes.
    x_ndc = 2.0 * cols.ravel() / camera.width - 1.0
    y_ndc = 2.0 * (camera.height - 1 - rows.ravel()) / camera.height - 1.0
    inverse = np.linalg.inv(map_to_clip(camera, pose))
    ends = []
    for z_ndc in (-1.0, 1.0):
        h = inverse @ np.stack([x_ndc, y_ndc, np.full_like(x_ndc, z_ndc), np.ones_like(x_ndc)])
        ends.append((h[:3] / h[3]).T)
    origin, direction = ends[0], ends[1] - ends[0]
    hit = np.ones(len(origin))  # ray parameter of the nearest hit: 1 is the far plane
    label = np.full(len(origin), -1)
    with np.errstate(divide="ignore"):
        floor_t = -origin[:, 2] / direction[:, 2]
    floor = (floor_t > 0) & (floor_t < 1)
    hit[floor], label[floor] = floor_t[floor], FLOOR
    for body, centre, size in boxes:
        low, high = np.array(centre) - np.array(size) / 2, np.array(centre) + np.array(size) / 2
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (low - origin) / direction, (high - origin) / direction
        t_in = np.nanmax(np.minimum(t1, t2), axis=1)
        t_out = np.nanmin(np.maximum(t1, t2), axis=1)
        nearer = (t_in <= t_out) & (t_in > 0) & (t_in < hit)
        hit[nearer], label[nearer] = t_in[nearer], body
    _, _, buffer = project(origin + hit[:, None] * direction, camera, pose)
    return label.reshape(rows.shape), buffer.reshape(rows.shape)


def test_camera_pose_looks_ahead_of_the_base_and_down() -> None:
    pose = camera_pose(1.0, 2.0, math.pi / 2, 0.3, 1.2, math.radians(30.0))
    assert pose[:3, 3] == pytest.approx([1.0, 2.3, 1.2])
    looking = -pose[:3, 2]
    assert looking == pytest.approx([0.0, math.cos(math.radians(30.0)), -0.5])
    assert pose[:3, 0] == pytest.approx([1.0, 0.0, 0.0])  # right of a base facing +y is +x
    assert column_major(view_matrix(pose)) @ pose == pytest.approx(np.eye(4))


def test_unproject_inverts_the_projection_pybullet_is_given() -> None:
    rng = np.random.default_rng(1)
    points = np.c_[rng.uniform(0.8, 2.5, 50), rng.uniform(-0.5, 0.5, 50), rng.uniform(0.0, 1.0, 50)]
    rows, cols, buffer = project(points, CAMERA, POSE)
    depth = linear_depth(buffer, CAMERA.near, CAMERA.far)
    assert unproject(rows, cols, depth, CAMERA, POSE) == pytest.approx(points, abs=1e-6)


def test_the_floor_unprojects_flat() -> None:
    labels, buffer = render([])
    rows, cols = np.nonzero(labels == FLOOR)
    depth = linear_depth(buffer[rows, cols], CAMERA.near, CAMERA.far)
    assert len(rows) > 1000
    assert unproject(rows, cols, depth, CAMERA, POSE)[:, 2] == pytest.approx(0.0, abs=1e-6)


def test_a_box_is_found_at_its_centre_not_on_its_near_face() -> None:
    box: Box = (7, (1.2, 0.1, 0.05), (0.06, 0.06, 0.1))
    labels, buffer = render([box])
    found = detect(labels, buffer, CAMERA, POSE, {7: Target("cup", 0.1)}, min_pixels=10, max_range=4.0)
    assert set(found) == {"cup"}
    pixel = 1.2 * CAMERA.tan_half_h * 2 / CAMERA.width  # a pixel's width at that distance, roughly
    assert found["cup"].centre == pytest.approx([1.2, 0.1, 0.05], abs=pixel)
    assert found["cup"].yaw is None, "no heading asked for a round object"


def test_centre_from_points_uses_the_extent_and_the_top() -> None:
    # The top and the near side of a 0.1 m cube centred at (1, 0, 0.05), seen from -x.
    top = [[1.0 + dx, dy, 0.1] for dx in (-0.05, 0.0, 0.05) for dy in (-0.05, 0.05)]
    side = [[0.95, dy, dz] for dy in (-0.05, 0.0, 0.05) for dz in (0.0, 0.05, 0.1)]
    points = np.array(top + side)
    assert points.mean(axis=0)[0] < 0.98, "the plain mean is pulled towards the camera"
    assert estimate_centre(points, 0.1) == pytest.approx([1.0, 0.0, 0.05])


def test_only_known_bodies_with_enough_pixels_in_range_and_inside_the_image_count() -> None:
    boxes: list[Box] = [
        (10, (1.2, 0.0, 0.05), (0.1, 0.1, 0.1)),  # plainly in view
        (11, (1.2, 0.4, 0.05), (0.1, 0.1, 0.1)),  # in view, but not a target (furniture, a person)
        (12, (1.5, -0.3, 0.015), (0.03, 0.03, 0.03)),  # a speck: a few pixels
        (13, (1.2, -1.6, 0.05), (0.1, 0.4, 0.1)),  # cut off by the right edge of the image
        (14, (2.6, 0.0, 0.1), (0.2, 0.2, 0.2)),  # in view, but farther than 2 m
    ]
    labels, buffer = render(boxes)
    assert {10, 11, 12, 13, 14} <= set(np.unique(labels).tolist()), "every box shows in the image"
    targets = {i: Target(f"box{i}", 0.1) for i in (10, 12, 13, 14)}
    found = detect(labels, buffer, CAMERA, POSE, targets, min_pixels=10, max_range=2.0)
    assert set(found) == {"box10"}
    assert set(detect(labels, buffer, CAMERA, POSE, targets, min_pixels=10, max_range=4.0)) == {"box10", "box14"}


def test_a_box_hidden_behind_another_is_not_seen() -> None:
    wall: Box = (20, (1.0, 0.0, 0.5), (0.1, 1.0, 1.0))
    cup: Box = (21, (1.3, 0.0, 0.05), (0.06, 0.06, 0.1))
    labels, buffer = render([wall, cup])
    assert 21 not in labels
    targets = {20: Target("wall", 1.0), 21: Target("cup", 0.1)}
    assert set(detect(labels, buffer, CAMERA, POSE, targets, min_pixels=1, max_range=4.0)) == {"wall"}
    labels, buffer = render([cup])
    assert set(detect(labels, buffer, CAMERA, POSE, targets, min_pixels=1, max_range=4.0)) == {"cup"}


@pytest.mark.parametrize("degrees", [0.0, 30.0, 89.0, -60.0])
def test_a_books_heading_comes_from_the_outline_of_its_points(degrees: float) -> None:
    # The top of a 6 x 20 cm book, sampled on a grid, turned by `degrees`.
    yaw = math.radians(degrees)
    xs, ys = np.meshgrid(np.linspace(-0.03, 0.03, 7), np.linspace(-0.1, 0.1, 21))
    c, s = math.cos(yaw), math.sin(yaw)
    points = np.stack([2.0 + c * xs - s * ys, 1.0 + s * xs + c * ys, np.full_like(xs, 0.5)], axis=-1).reshape(-1, 3)
    assert estimate_yaw(points, (0.06, 0.2)) == pytest.approx(yaw, abs=1e-6)
    # Points on a line (seen edge on) tell nothing.
    assert estimate_yaw(points[:7], (0.06, 0.2)) is None
