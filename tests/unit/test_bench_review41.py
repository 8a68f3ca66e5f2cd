"""The benches' pure logic: what counts as received, recorded, halted and met (bench/)."""

from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import msgspec
import pytest

from bench import estop, gate, parser, recorder, stream
from bench.service import BenchError, RobotMotion
from bench.transport import percentile
from schemas import keys
from schemas.common import Pose2D
from schemas.plan import PlanApproved
from schemas.robot import ARM_JOINTS, JointState, Odometry


class Subscriptions:
    """Stands in for a Node: keeps each topic's callback, to hand it messages."""

    def __init__(self) -> None:
        self.callbacks: dict[Any, Callable[[Any], None]] = {}

    def subscribe(self, topic: Any, callback: Callable[[Any], None]) -> None:
        self.callbacks[topic] = callback


def still_odom(stamp: float) -> Odometry:
    return Odometry(stamp=stamp, sim_time=0.0, pose=Pose2D(x=0.0, y=0.0), linear_x=0.0, angular_z=0.0)


def still_joints(stamp: float) -> JointState:
    return JointState(
        stamp=stamp, name=list(ARM_JOINTS), position=[0.0] * len(ARM_JOINTS), velocity=[0.0] * len(ARM_JOINTS)
    )


def test_a_halt_is_when_the_last_topic_came_still_even_if_its_sample_arrives_first() -> None:
    node = Subscriptions()
    motion = RobotMotion(node, arm=True)  # type: ignore[arg-type]

    def trigger() -> None:
        # The base is still from 10 ms on; the arm's sample saying it was still from 4 ms arrives after.
        node.callbacks[keys.ODOM](still_odom(motion.t0 + 0.010))
        node.callbacks[keys.JOINT_STATES](still_joints(motion.t0 + 0.004))

    assert motion.halt_ms(trigger, timeout=1.0) == pytest.approx(10.0, abs=1e-3)


def vetoes() -> stream.Vetoes:
    return stream.Vetoes(Subscriptions())  # type: ignore[arg-type]


def sent(stamps: list[float], arrivals: list[tuple[float, float]], seconds: float) -> stream.Stream:
    return stream.Stream(lambda _: None, sent=stamps, seconds=seconds, arrived=arrivals)


def test_a_twist_that_came_twice_does_not_make_up_for_one_lost() -> None:
    gate_stream = sent([100.0, 100.001, 100.002], [(100.0, 100.0005), (100.0, 100.0009), (100.001, 100.0015)], 0.003)

    result = stream.summary(gate_stream, sent([], [], 0.0), vetoes())

    assert (result["received"], result["lost"], result["duplicates"]) == (2, 1, 1)
    assert result["goals_met"]["nothing_lost"] is False
    assert any("more than once" in error for error in result["errors"])


def test_a_stream_slower_than_the_goals_rate_does_not_meet_it() -> None:
    stamps = [100.0 + i / 100 for i in range(100)]  # 100 Hz for 1 s, all arrived 1 ms later
    gate_stream = sent(stamps, [(stamp, stamp + 0.001) for stamp in stamps], 1.0)

    result = stream.summary(gate_stream, sent([], [], 0.0), vetoes())

    assert result["lost"] == 0
    assert result["goals_met"]["rate_hz"] is False


def test_goals_through_the_gate_are_not_met_when_some_were_rejected_or_failed() -> None:
    times = {kind.name: ([1.0] * 10, [1.1] * 10) for kind in gate.KINDS}

    clean = gate.summarize(gate.Samples(times))
    rejected = gate.summarize(gate.Samples(times, rejected=1))
    failed = gate.summarize(gate.Samples(times, failed=1))

    assert all(clean["goals_met"].values())
    assert rejected["goals_met"]["nothing_rejected"] is False
    assert failed["goals_met"]["nothing_failed"] is False


def test_a_plan_parsed_into_fewer_steps_is_an_error_not_a_faster_parse(monkeypatch: pytest.MonkeyPatch) -> None:
    from services.parser import parser as parsing

    real = parsing.parse

    def short(text: str, fmt: str) -> Any:
        plan = real(text, fmt)
        return msgspec.structs.replace(plan, steps=plan.steps[:9])

    monkeypatch.setattr(parsing, "parse", short)
    with pytest.raises(BenchError, match="9 steps, not 10"):
        parser.parse_times(parser.JSON_PLAN, "json", 0.01, 0)


def test_a_message_recorded_twice_does_not_make_up_for_one_lost() -> None:
    load = recorder.LoadFound(3)

    for data in (recorder.payload(0), recorder.payload(1), recorder.payload(1), b"not json", recorder.payload(7)):
        load.add(data)

    assert (load.found, load.extra) == (2, 3)


def test_a_quick_recorder_run_does_not_meet_the_goal() -> None:
    held = {"rate_hz": 40_000.0, "lost": 0, "duration_s": 30.0}

    assert all(recorder.goals_met(held).values())
    assert recorder.goals_met({**held, "duration_s": 2.0})["duration_s"] is False


class Echoing:
    """Stands in for the bench's Node: bare gets answered with their own bytes, plan checks approved."""

    robot = "r41"

    def __init__(self) -> None:
        self.asked: list[str] = []
        self.session = self

    def get(self, key: str, payload: bytes, timeout: float) -> list[Any]:
        self.asked.append(key)
        reply = SimpleNamespace(ok=SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: payload)), err=None)
        return [reply]

    def call(self, service: Any, request: Any, timeout: float) -> PlanApproved:
        return PlanApproved()


def test_the_plan_check_is_compared_with_safetys_own_echo_not_the_relay_to_the_robot() -> None:
    node = Echoing()
    state = SimpleNamespace(odom=SimpleNamespace(message=still_odom(1.0)))

    echoes, checks, _ = gate.plan_checks(SimpleNamespace(node=node), state, 3)  # type: ignore[arg-type]

    assert (len(echoes), len(checks)) == (3, 3)
    assert set(node.asked) == {keys.bench_echo_key(node.robot, "safety")}


@pytest.mark.parametrize(("n", "p99"), [(1, 1), (20, 20), (60, 60), (100, 99), (475, 471), (1000, 990)])
def test_a_p99_has_at_most_one_percent_of_the_samples_above_it(n: int, p99: int) -> None:
    samples = [float(i) for i in range(n, 0, -1)]  # 1 to n, in no sorted order

    assert percentile(samples, 99) == p99
    assert sum(s > p99 for s in samples) <= n / 100


def test_an_estop_run_of_a_few_trials_does_not_meet_the_goal() -> None:
    assert all(estop.goals_met([4.0] * 20).values())
    assert estop.goals_met([4.0] * 3) == {"p99_ms": True, "trials": False}
    assert estop.goals_met([4.0] * 19 + [11.0])["p99_ms"] is False
