"""The arm as pinocchio sees it, shared by the executor (IK, trajectories) and safety (limits, FK).

The Panda's seven arm joints from its URDF (fingers locked), its joint limits as the URDF states
them, forward kinematics of the grasp point, and the frames between the map, the base and the arm.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pinocchio as pin

from schemas.common import Pose2D, Vec3
from schemas.robot import ARM_JOINTS, FINGER_JOINTS
from services.worldmodel import arm_urdf_path as arm_urdf_path  # importable from here too, as before
from services.worldmodel import read_arm_urdf

GRASP_FRAME = "panda_grasptarget"
DEFAULT_ARM_URDF = "franka_panda/panda.urdf"


def map_to_base(base: Pose2D, x: float, y: float) -> tuple[float, float]:
    """A floor point (map frame) in the frame of the base standing at `base` (x ahead, y left)."""
    dx, dy = x - base.x, y - base.y
    c, s = math.cos(base.yaw), math.sin(base.yaw)
    return c * dx + s * dy, -s * dx + c * dy


def base_to_map(base: Pose2D, x: float, y: float) -> tuple[float, float]:
    """The inverse of map_to_base."""
    c, s = math.cos(base.yaw), math.sin(base.yaw)
    return base.x + c * x - s * y, base.y + s * x + c * y


def world_to_arm(base: Pose2D, mount: Vec3, point: Vec3) -> np.ndarray:
    """`point` (map frame) in the arm's base frame panda_link0, mounted at `mount` on the base."""
    x, y = map_to_base(base, point.x, point.y)
    return np.array([x - mount.x, y - mount.y, point.z - mount.z])


def arm_to_world(base: Pose2D, mount: Vec3, point: Sequence[float] | np.ndarray) -> Vec3:
    """The inverse of world_to_arm: a point in panda_link0 back in the map frame."""
    x, y = base_to_map(base, float(point[0]) + mount.x, float(point[1]) + mount.y)
    return Vec3(x=x, y=y, z=float(point[2]) + mount.z)


class ArmModel:
    """The seven arm joints of the Panda, fingers locked open, with the grasp target as end effector."""

    def __init__(self, arm_urdf: str | Path = DEFAULT_ARM_URDF) -> None:
        """ValueError naming robot.arm_urdf when it is no regular file, too large, or not UTF-8 (read_arm_urdf);
        pinocchio's own error when it is not a URDF."""
        # Read here, bounded, then parsed from memory: given the path, pinocchio opened anything.
        try:
            text = read_arm_urdf(arm_urdf).decode()
        except UnicodeDecodeError as exc:
            raise ValueError(f"robot.arm_urdf {str(arm_urdf)!r}: not UTF-8 text (byte {exc.start})") from None
        full = pin.buildModelFromXML(text)
        fingers = [full.getJointId(name) for name in FINGER_JOINTS if full.existJointName(name)]
        self.model = pin.buildReducedModel(full, fingers, pin.neutral(full))
        self.data = self.model.createData()
        # pinocchio's Data is scratch space: one computation at a time (safety checks and watches at once).
        self._lock = threading.Lock()
        self.joint_names: tuple[str, ...] = tuple(self.model.names[1:])
        if self.joint_names != ARM_JOINTS:
            raise ValueError(f"{arm_urdf} has joints {self.joint_names}, expected {ARM_JOINTS}")
        self.frame_id = self.model.getFrameId(GRASP_FRAME)
        self.lower = np.array(self.model.lowerPositionLimit)
        self.upper = np.array(self.model.upperPositionLimit)
        self.max_velocity = np.array(self.model.velocityLimit)

    def within_limits(self, q: Sequence[float] | np.ndarray) -> bool:
        q = np.asarray(q, dtype=float)
        return bool(np.all(q >= self.lower - 1e-9) and np.all(q <= self.upper + 1e-9))

    def forward(self, q: Sequence[float] | np.ndarray) -> pin.SE3:
        """The grasp target's pose in panda_link0. Safe to call from several threads."""
        with self._lock:
            pin.framesForwardKinematics(self.model, self.data, np.asarray(q, dtype=float))
            return self.data.oMf[self.frame_id].copy()

    def grasp_point(self, q: Sequence[float] | np.ndarray) -> np.ndarray:
        """Where the grasp target is, in panda_link0 (metres)."""
        return np.array(self.grasp_xyz(q))

    def grasp_xyz(self, q: Sequence[float] | np.ndarray) -> tuple[float, float, float]:
        """grasp_point as plain floats. Places only the grasp frame, where forward places every frame
        and copies the pose: the same doubles, some 20 us sooner in a check run after idling, as
        safety's are (82 against 103 us after 40 ms asleep, in process, 2026-11-29). Safe to call
        from several threads."""
        with self._lock:
            pin.forwardKinematics(self.model, self.data, np.asarray(q, dtype=float))
            x, y, z = pin.updateFramePlacement(self.model, self.data, self.frame_id).translation.tolist()
        return x, y, z
