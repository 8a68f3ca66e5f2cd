"""The Panda's top-down IK, frame conversions and timed joint trajectories."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from schemas.common import Pose2D, Vec3
from schemas.robot import ARM_JOINTS
from services.executor.errors import IKFailed
from services.executor.kinematics import ArmKinematics, joint_trajectory
from services.robotmodel import arm_to_world, world_to_arm

HOME = [0.0, -1.3, 0.0, -2.35, 0.0, 1.05, 0.785]


@pytest.fixture(scope="module")
def kin() -> ArmKinematics:
    return ArmKinematics()


def test_model_has_the_seven_arm_joints(kin: ArmKinematics) -> None:
    assert kin.joint_names == ARM_JOINTS
    assert kin.lower.shape == kin.upper.shape == (7,)
    assert kin.upper[3] <= 0.0  # joint 4 only bends one way


@pytest.mark.parametrize("target", [(0.35, -0.3, 0.45), (0.5, 0.2, 0.01), (0.45, 0.0, 0.6)])
def test_ik_reaches_target_with_the_hand_pointing_down(kin: ArmKinematics, target: tuple[float, float, float]) -> None:
    q = kin.solve_top_down(target, HOME)
    reached = kin.forward(q)
    assert np.linalg.norm(reached.translation - np.array(target)) < 2e-3
    hand_z = reached.rotation[:, 2]
    assert hand_z[2] < -0.999  # pointing straight down
    assert kin.within_limits(q)


def test_unreachable_target_raises_ik_failed_naming_target_and_residual(kin: ArmKinematics) -> None:
    with pytest.raises(IKFailed, match=r"\(1\.500, 0\.000, 0\.000\).*residual"):
        kin.solve_top_down((1.5, 0.0, 0.0), HOME)


def test_world_to_arm_and_back() -> None:
    base = Pose2D(x=2.5, y=1.05, yaw=-math.pi / 2)
    mount = Vec3(x=0.15, y=0.0, z=0.5)
    # A point 0.45 m ahead of the base (facing -y) and 0.1 m above the mount.
    in_arm = world_to_arm(base, mount, Vec3(x=2.5, y=0.6, z=0.6))
    assert np.allclose(in_arm, [0.3, 0.0, 0.1])
    back = arm_to_world(base, mount, in_arm)
    assert (back.x, back.y, back.z) == pytest.approx((2.5, 0.6, 0.6))


def test_trajectory_respects_the_speed_limit_and_ends_at_the_target() -> None:
    q_from = np.array(HOME)
    q_to = q_from + np.array([0.8, -0.3, 0.0, 0.5, 0.0, -0.2, 1.0])
    points = joint_trajectory(q_from, q_to, max_joint_speed=0.5)
    assert 3 <= len(points) <= 20
    assert points[0].time_from_start == 0.0
    assert np.allclose(points[-1].positions, q_to)
    for a, b in itertools.pairwise(points):
        dt = b.time_from_start - a.time_from_start
        assert dt > 0
        speed = np.max(np.abs(np.subtract(b.positions, a.positions))) / dt
        assert speed <= 0.5 + 1e-9


def test_trajectory_without_motion_is_still_well_formed() -> None:
    points = joint_trajectory(HOME, HOME, max_joint_speed=1.0)
    assert points[-1].time_from_start > 0
    assert np.allclose(points[-1].positions, HOME)
