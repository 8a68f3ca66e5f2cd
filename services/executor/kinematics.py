"""Panda arm kinematics on the mobile base: frames, inverse kinematics and timed joint trajectories."""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Sequence

import numpy as np
import pinocchio as pin

from schemas.common import Pose2D, Vec3
from schemas.robot import TrajectoryPoint
from services.executor.errors import IKFailed
from services.robotmodel import ArmModel

# Keep solutions a hair inside the limits so position control never pushes against a stop.
LIMIT_MARGIN = 0.01
# Reached means within a millimetre and about half a degree.
POSITION_TOLERANCE = 1e-3
ORIENTATION_TOLERANCE = 1e-2
# With the hand pointing down, yaw=0 puts the finger axis (the hand's y) along the arm's y.
TOP_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
# Restarts of the damped least squares: a fixed spread, so every answer is reproducible.
RANDOM_SEEDS = 6
SEED_RNG = 7
# A restart still this far off after so many iterations will not converge: give up on it.
STALLED = ((60, 0.05), (100, 0.01))
DAMPING = 1e-4
DAMPED_IDENTITY = DAMPING * np.eye(6)

# A test a solution must pass: collision-free, for the planner.
Accept = Callable[[np.ndarray], bool]
# What a solution the test turned down runs into ("panda_hand touches kitchen_counter"), for the message.
Explain = Callable[[np.ndarray], str]
# A message names at most this many different reasons solutions were turned down.
REASONS_SHOWN = 3


def rotation_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def arm_from_map(base: Pose2D, mount: Vec3) -> pin.SE3:
    """The rigid transform taking map-frame poses into panda_link0, the base standing at `base` (the
    same mapping as world_to_arm, for poses)."""
    rotation = rotation_z(-base.yaw)
    translation = -rotation @ np.array([base.x, base.y, 0.0]) - np.array([mount.x, mount.y, mount.z])
    return pin.SE3(rotation, translation)


def top_down_rotation(yaw: float) -> np.ndarray:
    """The hand pointing straight down (its z along -z), turned by `yaw` about the vertical."""
    return rotation_z(yaw) @ TOP_DOWN


def hand_rotation(approach: Sequence[float] | np.ndarray, fingers: Sequence[float] | np.ndarray) -> np.ndarray:
    """The grasp frame's orientation with its z along `approach` (palm towards fingertips) and its y,
    the axis the fingers close along, along `fingers` made perpendicular to the approach."""
    z = np.asarray(approach, dtype=float)
    z = z / np.linalg.norm(z)
    y = np.asarray(fingers, dtype=float)
    y = y - (y @ z) * z
    norm = float(np.linalg.norm(y))
    if norm < 1e-9:
        raise ValueError(f"the finger axis {list(fingers)} is parallel to the approach {list(approach)}")
    y = y / norm
    return np.column_stack([np.cross(y, z), y, z])


class ArmKinematics(ArmModel):
    """The arm model with inverse kinematics for any hand pose and timed trajectories."""

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
        try:
            return self.solve(pin.SE3(top_down_rotation(yaw), target), q_seed, max_iterations=max_iterations)
        except IKFailed as exc:
            x, y, z = (float(v) for v in target)
            raise IKFailed(f"no top-down IK for target ({x:.3f}, {y:.3f}, {z:.3f}) m in panda_link0: {exc}") from None

    def solve(
        self,
        desired: pin.SE3,
        q_seed: Sequence[float] | np.ndarray,
        *,
        accept: Accept | None = None,
        explain: Explain | None = None,
        seeds: Sequence[np.ndarray] = (),
        random_seeds: int = RANDOM_SEEDS,
        margin: float = LIMIT_MARGIN,
        max_iterations: int = 300,
    ) -> np.ndarray:
        """Joint positions putting the grasp frame at `desired` (position and orientation in panda_link0).

        Damped least squares from `q_seed`, then from `seeds`, then (unless `random_seeds` is 0) the
        middle of the joint ranges and `random_seeds` fixed spread ones, in that order: the first
        converged solution that `accept` takes (collision-free, say) wins, so the answer is
        deterministic. Solutions stay `margin` inside the joint limits. Raises IKFailed with the best
        residual, or with how many solutions `accept` turned down and, given `explain`, what they
        run into.
        """
        data = self.model.createData()  # own scratch space: callers on other threads use self.data
        lower, upper = self.lower + margin, self.upper - margin
        best_q, best_residual = np.asarray(q_seed, dtype=float), math.inf
        rejected: list[np.ndarray] = []
        for seed in self._seeds(np.asarray(q_seed, dtype=float), seeds, random_seeds):
            q, residual, converged = self._dls(data, desired, np.clip(seed, lower, upper), lower, upper, max_iterations)
            if residual < best_residual:
                best_q, best_residual = q, residual
            if not converged:
                continue
            if accept is None or accept(q):
                return q
            rejected.append(q)
        if rejected:
            raise IKFailed(_turned_down(rejected, explain))
        raise IKFailed(f"best residual {best_residual:.3f} m at joints {np.round(best_q, 3).tolist()}")

    def _seeds(self, q_seed: np.ndarray, extra: Sequence[np.ndarray], random_seeds: int) -> list[np.ndarray]:
        # Deterministic restarts: the caller's seeds, then the middle of the range and a fixed spread.
        given = [q_seed, *(np.asarray(s, dtype=float) for s in extra)]
        if random_seeds == 0:
            return given
        rng = np.random.default_rng(SEED_RNG)
        spread = [rng.uniform(self.lower, self.upper) for _ in range(random_seeds)]
        return [*given, (self.lower + self.upper) / 2, *spread]

    def _dls(
        self,
        data: pin.Data,
        desired: pin.SE3,
        q: np.ndarray,
        lower: np.ndarray,
        upper: np.ndarray,
        max_iterations: int,
    ) -> tuple[np.ndarray, float, bool]:
        """Damped least squares on the 6-D error in the grasp frame; the joints clipped to [lower, upper]."""
        step = 0.5
        for iteration in range(max_iterations + 1):
            # The Jacobian's forward kinematics also gives the pose: one pass per iteration.
            pin.computeJointJacobians(self.model, data, q)
            current = pin.updateFramePlacement(self.model, data, self.frame_id)
            # The desired pose seen from the current one: its translation is as long as the gap
            # between the two positions, and its log's angular part is the rotation between them.
            local = current.actInv(desired)
            error = pin.log6(local).vector
            residual = math.hypot(*local.translation)
            if residual < POSITION_TOLERANCE and math.hypot(*error[3:]) < ORIENTATION_TOLERANCE:
                return q, residual, True
            if iteration == max_iterations or any(iteration >= n and residual > off for n, off in STALLED):
                break
            jacobian = pin.Jlog6(local.inverse()) @ pin.getFrameJacobian(self.model, data, self.frame_id, pin.LOCAL)
            dq = jacobian.T @ np.linalg.solve(jacobian @ jacobian.T + DAMPED_IDENTITY, error)
            q = np.clip(pin.integrate(self.model, q, step * dq), lower, upper)
        return q, residual, False


def _turned_down(rejected: list[np.ndarray], explain: Explain | None) -> str:
    """'all 3 solutions found collide: panda_hand touches shelf (2 of them); panda_link7 touches shelf'."""
    what = f"all {len(rejected)} solutions found collide"
    if explain is None:
        return what
    reasons = Counter(explain(q) or "nothing named" for q in rejected)
    shown = [
        f"{reason} ({count} of them)" if count > 1 and len(reasons) > 1 else reason
        for reason, count in sorted(reasons.items(), key=lambda item: (-item[1], item[0]))[:REASONS_SHOWN]
    ]
    more = f"; and {len(reasons) - REASONS_SHOWN} other contacts" if len(reasons) > REASONS_SHOWN else ""
    return f"{what}: " + "; ".join(shown) + more


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
