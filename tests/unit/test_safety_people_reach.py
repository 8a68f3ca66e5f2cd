"""People near an arm whose position safety does not know (joint states missing, stale or naming too
few joints): the hand counts as anywhere within the arm's full reach of the base's centre, as
navigation assumes (policy.reach(None)), never as stowed over the base."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from schemas.common import Pose2D
from schemas.robot import ARM_JOINTS, JointState
from schemas.world import PerceivedHuman, PerceivedHumans
from services.safety.gate import SafetyGate
from services.safety.latch import EstopLatch
from services.safety.monitor import Separation
from services.safety.policy import SafetyPolicy
from tests.unit.test_safety_gate import HERE, TICK, TOKEN, WORLD, FakeClock, odom
from tests.unit.test_safety_gate import policy as policy  # the module-scoped fixture, shared

STOWED = list(WORLD.robot.home_joints)  # the hand over the base, inside its footprint


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock(10.0)


@pytest.fixture
def gate(policy: SafetyPolicy, clock: FakeClock) -> SafetyGate:
    return SafetyGate(policy, EstopLatch(TOKEN), clock, FakeClock())


def arm(names: list[str], positions: list[float]) -> JointState:
    return JointState(stamp=0.0, name=names, position=positions, velocity=[0.0] * len(names))


def person_ahead(gate: SafetyGate, gap: float) -> Separation:
    """The operator `gap` from the base's front edge (body to footprint), with fresh odometry; the
    separation one heartbeat later."""
    front = WORLD.robot.base_size.x / 2
    body = HERE.x + front + gate.policy.policy.humans.person_radius + gap
    gate.odometry(odom())
    gate.humans(
        PerceivedHumans(stamp=0.0, humans=[PerceivedHuman(id="ann", name="ann", pose=Pose2D(x=body, y=HERE.y))])
    )
    gate.tick()
    return gate.separation


def never_reported(gate: SafetyGate, clock: FakeClock) -> None:
    pass


def stale(gate: SafetyGate, clock: FakeClock) -> None:
    gate.joint_state(arm(list(ARM_JOINTS), STOWED))
    clock.advance(gate.policy.policy.monitor.state_max_age + TICK)


def a_joint_missing(gate: SafetyGate, clock: FakeClock) -> None:
    gate.joint_state(arm(list(ARM_JOINTS[:-1]), STOWED[:-1]))


@pytest.mark.parametrize("unknown", [never_reported, stale, a_joint_missing])
def test_a_person_within_reach_of_an_arm_whose_joints_are_unknown_pauses_the_robot(
    gate: SafetyGate, clock: FakeClock, unknown: Callable[[SafetyGate, FakeClock], None]
) -> None:
    humans = gate.policy.policy.humans
    unknown(gate, clock)
    # Half a metre from the footprint: reduced speed for a stowed arm, within reach of one held out.
    found = person_ahead(gate, 0.5)
    assert found.scale == 0.0, found
    assert found.distance == 0.0 and found.person == "ann"
    assert "ann is 0.00 m away" in found.reason and "joints are unknown" in found.reason
    assert f"reaching out {gate.policy.reach(None):.2f} m" in found.reason
    # The same person with the arm reported stowed: the footprint's distance decides.
    clock.advance(humans.unseen_after + TICK)
    gate.joint_state(arm(list(ARM_JOINTS), STOWED))
    stowed = person_ahead(gate, 0.5)
    assert stowed.scale == humans.reduced_speed_scale
    assert stowed.distance == pytest.approx(0.5)
    assert "joints are unknown" not in stowed.reason


def test_with_joints_unknown_the_distance_is_from_the_arms_full_reach(gate: SafetyGate, clock: FakeClock) -> None:
    humans = gate.policy.policy.humans
    reach, front = gate.policy.reach(None), WORLD.robot.base_size.x / 2
    assert reach > front, "the test needs an arm that reaches beyond the base"
    # 0.6 m beyond where the hand may be: slowed, measured from there, not from the footprint.
    found = person_ahead(gate, reach - front + 0.6)
    assert found.scale == humans.reduced_speed_scale
    assert found.distance == pytest.approx(0.6)
    # Beyond D of the arm's full reach: full speed, whatever the arm does (once the report above
    # no longer counts).
    clock.advance(humans.unseen_after + TICK)
    far = person_ahead(gate, reach - front + humans.slow_distance + humans.release_margin + 0.05)
    assert far.scale == 1.0 and far.reason == ""


def test_people_reported_while_the_robots_pose_is_unknown_pause_it(gate: SafetyGate) -> None:
    """It was reduced speed, though no distance to them could be had (the README: then 0)."""
    gate.humans(
        PerceivedHumans(stamp=0.0, humans=[PerceivedHuman(id="ann", name="ann", pose=Pose2D(x=HERE.x + 3.0, y=HERE.y))])
    )
    gate.tick()
    assert gate.separation.scale == 0.0 and "pose is unknown" in gate.separation.reason, gate.separation
