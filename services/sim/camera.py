"""The robot's depth camera: pybullet renders segmentation and depth, detection.py turns them into objects."""

from __future__ import annotations

import base64
import io
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import pybullet

from schemas.common import Pose2D
from services.sim.config import CameraConfig
from services.sim.detection import Detection, Intrinsics, Target, camera_pose, detect, view_matrix


def png(pixels: np.ndarray) -> bytes:
    """An RGB image (height x width x 3, uint8) as PNG."""
    # Here, not at the top: only the process that draws pictures (the sim's renderer) loads Pillow.
    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(pixels, mode="RGB").save(out, format="PNG", optimize=False)
    return out.getvalue()


def png_base64(pixels: np.ndarray) -> str:
    """An RGB image as a base64 PNG, as MCP image content carries it."""
    return base64.b64encode(png(pixels)).decode()


@dataclass(frozen=True)
class Frame:
    """One rendered image: where the camera was (camera-to-map, 4x4) and what each pixel saw."""

    pose: np.ndarray
    segmentation: np.ndarray  # the body unique id per pixel, -1 where nothing was hit
    depth_buffer: np.ndarray  # OpenGL depth in [0, 1]


class Camera:
    """A camera on the mobile base, rendered with the CPU renderer (pybullet DIRECT has no GPU)."""

    def __init__(self, bullet: Any, config: CameraConfig, floor: int | None = None, robot: int | None = None) -> None:
        """`floor`: the body the world stands on, drawn only in pictures. It hides nothing the
        detector looks for, yet fills about two thirds of a frame from the start pose, and pybullet's
        CPU renderer pays per pixel drawn: about 7.5 ms a frame with it, 3 without. `robot`: the
        robot's body, whose hand above an object hides part of it, and the part left would put its
        centre off (detection.detect leaves such an object out)."""
        self.bullet = bullet
        self.config = config
        self._floor = floor
        self.show_floor(False)
        self._robot = () if robot is None else (robot,)
        self.intrinsics = Intrinsics(
            width=config.width,
            height=config.height,
            hfov=math.radians(config.hfov_deg),
            near=config.near,
            far=config.max_range,
        )
        self._projection = self.intrinsics.projection_matrix()
        self._noise = np.random.default_rng(config.seed)
        # The last frame, for a camera told when the scene moves (keep_frames): services/sim/renderer.py.
        self._kept: Frame | None = None
        self._keeps = False

    def keep_frames(self) -> None:
        """From now on, draw a frame only after `scene_moved` (else the last one is used again): for an
        owner that tells this camera whenever anything in the world, the robot included, may have moved."""
        self._keeps = True

    def scene_moved(self) -> None:
        self._kept = None

    def show_floor(self, shown: bool) -> None:
        """Draw the floor in what is rendered next, or not (pictures draw it; see __init__)."""
        # The CPU renderer skips a body that is wholly transparent.
        if self._floor is not None:
            self.bullet.changeVisualShape(self._floor, -1, rgbaColor=[1.0, 1.0, 1.0, 1.0 if shown else 0.0])

    def pose(self, base: Pose2D) -> np.ndarray:
        c = self.config
        return camera_pose(base.x, base.y, base.yaw, c.mount_x, c.mount_z, math.radians(c.pitch_deg))

    def render(self, base: Pose2D) -> Frame:
        if self._kept is not None:
            return self._kept
        pose = self.pose(base)
        shape = (self.intrinsics.height, self.intrinsics.width)
        _, _, _, depth, segmentation = self.bullet.getCameraImage(
            self.intrinsics.width,
            self.intrinsics.height,
            viewMatrix=view_matrix(pose),
            projectionMatrix=self._projection,
            shadow=0,
            renderer=pybullet.ER_TINY_RENDERER,
        )
        frame = Frame(pose=pose, segmentation=np.reshape(segmentation, shape), depth_buffer=np.reshape(depth, shape))
        if self._keeps:
            self._kept = frame
        return frame

    def picture(self, base: Pose2D, scale: int = 2) -> np.ndarray:
        """A colour image (height x width x 3, uint8) from a base at `base`, `scale` times the
        detector's resolution: what a person or a model looks at, not what perception uses."""
        pose = self.pose(base)
        width, height = self.intrinsics.width * scale, self.intrinsics.height * scale
        self.show_floor(True)
        try:
            _, _, rgba, _, _ = self.bullet.getCameraImage(
                width,
                height,
                viewMatrix=view_matrix(pose),
                projectionMatrix=self._projection,
                shadow=1,
                renderer=pybullet.ER_TINY_RENDERER,
            )
        finally:
            self.show_floor(False)
        return np.reshape(np.asarray(rgba, dtype=np.uint8), (height, width, 4))[:, :, :3].copy()

    def look(self, base: Pose2D, targets: Mapping[int, Target]) -> dict[str, Detection]:
        """Where the camera, from a base at `base`, sees each of `targets` (by name): map-frame centres
        with the configured noise, and headings. Targets out of view, out of range, hidden, or partly
        hidden by the robot itself are missing."""
        frame = self.render(base)
        seen = detect(
            frame.segmentation,
            frame.depth_buffer,
            self.intrinsics,
            frame.pose,
            targets,
            min_pixels=self.config.min_pixels,
            max_range=self.config.max_range,
            occluders=self._robot,
        )
        return {
            name: Detection(found.centre + self._noise.normal(0.0, self.config.noise, 3), found.yaw)
            for name, found in seen.items()
        }
