"""Shared mode and the hand held out: the twist shared mode sends, after its guard changed it, is
held to the same horizon check (the hand's reach into keep-out zones) as the twist it was made from."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from schemas.common import Pose2D
from schemas.robot import ARM_JOINTS, JointState, Twist
from schemas.safety import ControlMode, Decision, ModeRequest, Rule
from schemas.world import PerceivedHumans
from services.safety.gate import Ruling, SafetyGate
from services.safety.latch import EstopLatch
from services.safety.modes import ModeFile
from services.safety.policy import SafetyPolicy
from tests.unit.test_safety_gate import TOKEN, WORLD, FakeClock, odom
from tests.unit.test_safety_gate import policy as policy  # the module-scoped fixture, shared

STOWED = list(WORLD.robot.home_joints)
HELD_OUT = [*STOWED[:1], 1.0, STOWED[2], -0.5, *STOWED[4:]]  # the hand 0.82 m ahead of the base's centre
# The hallway, heading north towards the stairs (keep-out, y 7 to 9 from x 10.5), the base's right
# side 1 cm from the east wall (x 11.95): turning, in place or driving, would swing a corner into it.
EAST_WALL = 11.95
OPEN = Pose2D(x=9.0, y=6.0, yaw=math.pi / 2)
# A full-speed left turn (0.6 m/s, 1.2 rad/s) gets 0.47 m nearer the stairs within the horizon (1 s),
# curving away from them; driving straight at 0.6 m/s, 0.6 m.
ARC = Twist(linear_x=0.6, angular_z=1.2)
AHEAD = 0.48  # in between: the centre this much further from the stairs than the hand reaches


def by_the_wall(reach: float) -> Pose2D:
    """Where the hand held out `reach` from the centre keeps out of the stairs on the arc, not straight
    on (the base's back 2 cm or more from the hallway's south wall)."""
    half_width = WORLD.robot.base_size.y / 2
    return Pose2D(x=EAST_WALL - half_width - 0.01, y=7.0 - reach - AHEAD, yaw=math.pi / 2)


def shared_gate(policy: SafetyPolicy, clock: FakeClock, tmp_path: Path) -> SafetyGate:
    gate = SafetyGate(policy, EstopLatch(TOKEN), clock, FakeClock(), modes=ModeFile(tmp_path / "mode.json"))
    assert gate.set_mode(ModeRequest(operator="alice", token=TOKEN, mode=ControlMode.SHARED)).forward.ok
    return gate


def teleop_at(gate: SafetyGate, clock: FakeClock, pose: Pose2D, joints: list[float] | None) -> Ruling[Twist | None]:
    clock.advance(0.05)
    gate.odometry(odom(pose=pose))
    if joints is not None:
        gate.joint_state(JointState(stamp=0.0, name=list(ARM_JOINTS), position=joints))
    gate.humans(PerceivedHumans(stamp=0.0, humans=[]))
    gate.tick()
    return gate.teleop(ARC)


@pytest.mark.parametrize("joints", [HELD_OUT, None], ids=["held_out", "unknown"])
def test_a_twist_the_guard_straightened_may_not_take_the_hand_into_a_keep_out_zone(
    policy: SafetyPolicy, tmp_path: Path, joints: list[float] | None
) -> None:
    clock = FakeClock()
    gate = shared_gate(policy, clock, tmp_path)
    reach = policy.reach(None if joints is None else dict(zip(ARM_JOINTS, joints, strict=True)))
    assert reach > policy.radius + 0.3, "the hand must stick out well beyond the footprint"
    for _ in range(12):  # up to speed on the arc, in the open
        ruling = teleop_at(gate, clock, OPEN, joints)
    assert ruling.forward == ARC
    # By the wall the guard drops the turn and drives on straight: the hand would reach the stairs.
    ruling = teleop_at(gate, clock, by_the_wall(reach), joints)
    (event,) = ruling.events
    assert ruling.forward == Twist(), event.reason
    assert (event.decision, event.rule) == (Decision.VETOED, Rule.CMD_VEL_HORIZON)
    assert event.reason.startswith("shared: kept off the outer wall, ")
    assert "hand" in event.reason and "keep-out zone 'stairs'" in event.reason and "base stopped" in event.reason


def test_with_the_arm_stowed_the_guard_still_drives_on_straight_along_the_wall(
    policy: SafetyPolicy, tmp_path: Path
) -> None:
    clock = FakeClock()
    gate = shared_gate(policy, clock, tmp_path)
    for _ in range(12):
        teleop_at(gate, clock, OPEN, STOWED)
    ruling = teleop_at(gate, clock, by_the_wall(policy.reach(None)), STOWED)
    (event,) = ruling.events
    assert ruling.forward is not None and ruling.forward.angular_z == 0.0
    assert ruling.forward.linear_x == pytest.approx(ARC.linear_x, abs=0.01)
    assert (event.decision, event.rule) == (Decision.CLAMPED, Rule.OBSTACLE)
    assert "turn dropped" in event.reason and event.values["shared"] == 1.0
