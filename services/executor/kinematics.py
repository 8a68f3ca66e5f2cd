"""Panda arm kinematics on the mobile base: frames, top-down IK and timed joint trajectories."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np
import pinocchio as pin

from schemas.common import Pose2D, Vec3
from schemas.robot import TrajectoryPoint
from services.executor.errors import IKFailed
from services.robotmodel import ArmModel, arm_to_world, world_to_arm

# Keep solutions a hair inside the limits so position control never pushes against a stop.
LIMIT_MARGIN = 0.01
# Reached means within a millimetre and about half a degree.
POSITION_TOLERANCE = 1e-3
ORIENTATION_TOLERANCE = 1e-2
# With the hand pointing down, yaw=0 puts the finger axis (the hand's y) along the arm's y.
TOP_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def top_down_rotation(yaw: float) -> np.ndarray:
    """The hand pointing straight down (its z along -z), turned by `yaw` about the vertical."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ TOP_DOWN


class ArmKinematics(ArmModel):
    """The arm model with top-down inverse kinematics and timed trajectories."""

    # The module's frame and trajectory helpers, also reachable from an instance.

    @staticmethod
    def world_to_arm(base: Pose2D, mount: Vec3, point: Vec3) -> np.ndarray:
        return world_to_arm(base, mount, point)

    @staticmethod
    def arm_to_world(base: Pose2D, mount: Vec3, point: Sequence[float] | np.ndarray) -> Vec3:
        return arm_to_world(base, mount, point)

    @staticmethod
    def joint_trajectory(
        q_from: Sequence[float] | np.ndarray, q_to: Sequence[float] | np.ndarray, max_joint_speed: float
    ) -> list[TrajectoryPoint]:
        return joint_trajectory(q_from, q_to, max_joint_speed)

    def straight_line(
        self,
        q_start: Sequence[float] | np.ndarray,
        target: Sequence[float] | np.ndarray,
        yaw: float = 0.0,
        *,
        step: float = 0.02,
        max_joint_jump: float = 0.35,
    ) -> list[np.ndarray]:
        """Joint waypoints moving the grasp target in a straight line to `target`, hand down.

        Near objects a joint-space interpolation would swing the fingers sideways; this keeps the
        fingertips on the line. Raises IKFailed when a point is unreachable or the arm would have to
        jump to another configuration on the way.
        """
        start = self.forward(q_start).translation
        goal = np.asarray(target, dtype=float)
        count = max(1, math.ceil(float(np.linalg.norm(goal - start)) / step))
        path = [np.asarray(q_start, dtype=float)]
        for k in range(1, count + 1):
            q = self.solve_top_down(start + (goal - start) * k / count, path[-1], yaw)
            jump = float(np.max(np.abs(q - path[-1])))
            if jump > max_joint_jump:
                raise IKFailed(
                    f"no continuous straight path to {np.round(goal, 3).tolist()}: "
                    f"a joint would jump {jump:.2f} rad at step {k} of {count}"
                )
            path.append(q)
        return path

    def solve_top_down(
        self,
        target: Sequence[float] | np.ndarray,
        q_seed: Sequence[float] | np.ndarray,
        yaw: float = 0.0,
        *,
        max_iterations: int = 300,
    ) -> np.ndarray:
        """Joint positions putting the grasp target at `target` (panda_link0), hand pointing down.

        Damped least squares from `q_seed`, then from a few spread seeds; raises IKFailed with the
        best residual when no start converges within the joint limits.
        """
        target = np.asarray(target, dtype=float)
        desired = pin.SE3(top_down_rotation(yaw), target)
        best_q, best_residual = np.asarray(q_seed, dtype=float), math.inf
        for seed in self._seeds(np.asarray(q_seed, dtype=float)):
            q, residual = self._dls(desired, seed, max_iterations)
            if residual < best_residual:
                best_q, best_residual = q, residual
            if self._converged(desired, q):
                return q
        x, y, z = (float(v) for v in target)
        raise IKFailed(
            f"no top-down IK for target ({x:.3f}, {y:.3f}, {z:.3f}) m in panda_link0: best residual "
            f"{best_residual:.3f} m at joints {np.round(best_q, 3).tolist()}"
        )

    def _seeds(self, q_seed: np.ndarray) -> list[np.ndarray]:
        # Deterministic restarts: the caller's seed, the middle of the range, then a fixed spread.
        rng = np.random.default_rng(7)
        middle = (self.lower + self.upper) / 2
        spread = [rng.uniform(self.lower, self.upper) for _ in range(6)]
        return [self._clip(q_seed), middle, *spread]

    def _clip(self, q: np.ndarray) -> np.ndarray:
        return np.clip(q, self.lower + LIMIT_MARGIN, self.upper - LIMIT_MARGIN)

    def _error(self, desired: pin.SE3, q: np.ndarray) -> tuple[np.ndarray, pin.SE3]:
        current = self.forward(q)
        local = current.actInv(desired)
        return pin.log6(local).vector, local

    def _converged(self, desired: pin.SE3, q: np.ndarray) -> bool:
        current = self.forward(q)
        position_error = float(np.linalg.norm(current.translation - desired.translation))
        orientation_error = float(np.linalg.norm(pin.log3(current.rotation.T @ desired.rotation)))
        return position_error < POSITION_TOLERANCE and orientation_error < ORIENTATION_TOLERANCE

    def _dls(self, desired: pin.SE3, q: np.ndarray, max_iterations: int) -> tuple[np.ndarray, float]:
        damping = 1e-4
        step = 0.5
        q = self._clip(q.copy())
        error, local = self._error(desired, q)
        for _ in range(max_iterations):
            if self._converged(desired, q):
                break
            jacobian = pin.computeFrameJacobian(self.model, self.data, q, self.frame_id, pin.LOCAL)
            jacobian = pin.Jlog6(local.inverse()) @ jacobian
            dq = jacobian.T @ np.linalg.solve(jacobian @ jacobian.T + damping * np.eye(6), error)
            q = self._clip(pin.integrate(self.model, q, step * dq))
            error, local = self._error(desired, q)
        residual = float(np.linalg.norm(self.forward(q).translation - desired.translation))
        return q, residual


def joint_trajectory(
    q_from: Sequence[float] | np.ndarray,
    q_to: Sequence[float] | np.ndarray,
    max_joint_speed: float,
    *,
    points: int = 8,
    min_duration: float = 0.2,
) -> list[TrajectoryPoint]:
    """A smooth (smoothstep) move from q_from to q_to, sampled so no joint exceeds the speed.

    Smoothstep peaks at 1.5x the mean speed, so the duration is stretched by that factor; linear
    interpolation between the samples then never goes faster than the peak.
    """
    if max_joint_speed <= 0:
        raise ValueError(f"max_joint_speed must be positive, got {max_joint_speed}")
    start = np.asarray(q_from, dtype=float)
    delta = np.asarray(q_to, dtype=float) - start
    duration = max(min_duration, 1.5 * float(np.max(np.abs(delta), initial=0.0)) / max_joint_speed)
    trajectory = [TrajectoryPoint(positions=start.tolist(), time_from_start=0.0)]
    for k in range(1, points + 1):
        tau = k / points
        blend = tau * tau * (3.0 - 2.0 * tau)
        trajectory.append(TrajectoryPoint(positions=(start + blend * delta).tolist(), time_from_start=duration * tau))
    return trajectory


def waypoint_trajectory(
    waypoints: Sequence[Sequence[float] | np.ndarray], max_joint_speed: float, *, min_segment: float = 0.05
) -> list[TrajectoryPoint]:
    """Time a dense joint path so that no joint exceeds the speed on any segment."""
    if max_joint_speed <= 0:
        raise ValueError(f"max_joint_speed must be positive, got {max_joint_speed}")
    qs = [np.asarray(q, dtype=float) for q in waypoints]
    t = 0.0
    trajectory = [TrajectoryPoint(positions=qs[0].tolist(), time_from_start=0.0)]
    for q0, q1 in itertools.pairwise(qs):
        # A margin over the bare minimum: the controller lags a little behind a fast ramp.
        t += max(min_segment, 1.25 * float(np.max(np.abs(q1 - q0), initial=0.0)) / max_joint_speed)
        trajectory.append(TrajectoryPoint(positions=q1.tolist(), time_from_start=t))
    return trajectory
