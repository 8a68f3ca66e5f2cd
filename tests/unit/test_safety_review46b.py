"""Review 46b: a flood on world/humans (the schema bounds neither the reports nor the people in one)
must not make safety's heartbeat late, and must never hide a person: a report not kept pauses the
robot until it would have left the window anyway."""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import services.safety.monitor as monitor
from schemas.common import Pose2D
from schemas.safety import ControlMode
from schemas.world import PerceivedHuman, PerceivedHumans
from services.safety.gate import SafetyGate
from services.safety.latch import EstopLatch
from services.safety.modes import ModeFile
from services.safety.monitor import PeopleReports, Person
from services.safety.policy import SafetyPolicy
from tests.unit.test_gate_incidents import WALL, ZONE_X, ZONE_Y, Clock, FakeStore, at, zone
from tests.unit.test_safety_gate import HERE, TICK, TOKEN, FakeClock, odom
from tests.unit.test_safety_gate import policy as policy  # the module-scoped fixture, shared

# Far more people within the window than any household's cameras report, and than a heartbeat can
# measure the distance to within its period.
FLOOD_REPORTS, PEOPLE_EACH = 500, 100
HEARTBEAT_BUDGET = 10_000  # distances measured in one heartbeat, at most
DEADLINE = 10.0  # s, for a state file to be read


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock(10.0)


@pytest.fixture
def gate(policy: SafetyPolicy, clock: FakeClock) -> SafetyGate:
    return SafetyGate(policy, EstopLatch(TOKEN), clock, FakeClock())


def report(*where: tuple[float, float]) -> PerceivedHumans:
    humans = [PerceivedHuman(id=f"p{i}", name=f"p{i}", pose=Pose2D(x=x, y=y)) for i, (x, y) in enumerate(where)]
    return PerceivedHumans(stamp=0.0, humans=humans)


FAR = [(HERE.x + 40.0, HERE.y)] * PEOPLE_EACH  # far beyond slow_distance


def test_a_flood_of_people_reports_does_not_make_the_heartbeat_measure_every_one(
    gate: SafetyGate, monkeypatch: pytest.MonkeyPatch
) -> None:
    gate.odometry(odom())
    for _ in range(FLOOD_REPORTS):
        gate.humans(report(*FAR))
    measured = 0
    real = monitor.distance_to_footprint

    def counting(*args: Any) -> float:
        nonlocal measured
        measured += 1
        return real(*args)

    monkeypatch.setattr(monitor, "distance_to_footprint", counting)
    gate.tick()
    assert measured <= HEARTBEAT_BUDGET, f"one heartbeat measured {measured} people"
    assert gate.separation.scale == 0.0, "reports were not all kept: someone may be beside the robot"


def test_a_person_in_a_report_not_kept_pauses_the_robot_until_it_is_out_of_the_window(
    gate: SafetyGate, clock: FakeClock
) -> None:
    window = gate.policy.policy.humans.unseen_after
    gate.odometry(odom())
    for _ in range(FLOOD_REPORTS):
        gate.humans(report(*FAR))
    beside = (HERE.x + 0.5, HERE.y)
    gate.humans(report(beside))  # beyond the limit: not kept
    gate.tick()
    assert gate.separation.scale == 0.0
    assert "not counted" in gate.separation.reason, gate.separation.reason
    # Still paused while the report not kept would be within the window, however many report nobody.
    clock.advance(window - TICK)
    gate.odometry(odom())
    gate.humans(report())
    gate.tick()
    assert gate.separation.scale == 0.0, gate.separation.reason
    clock.advance(2 * TICK)
    gate.odometry(odom())
    gate.humans(report())
    gate.tick()
    assert gate.separation.scale == 1.0, gate.separation.reason


def test_people_reports_keep_a_bounded_number_of_entries_and_say_when_they_were_flooded() -> None:
    reports = PeopleReports(window=1.0, limit=10)
    alice = Person("alice", 1.0, 0.0)
    for i in range(4):
        reports.add(0.1 * i, [alice])  # two entries each: the report and alice
    assert not reports.flooded(0.3)
    reports.add(0.35, [alice])  # 10 entries: still within the limit
    assert not reports.flooded(0.35)
    for _ in range(1000):
        reports.add(0.4, [])  # empty reports count too: each is one to go through
    assert reports.flooded(0.4)
    assert reports.people(0.4) == [alice] * 5
    assert reports.flooded(1.4)
    assert not reports.flooded(1.4 + 1e-6)
    assert reports.people(1.4 + 1e-6) is None, "every report kept is out of the window too"


# A caution zone while the base's pose is unknown


def test_a_caution_zone_s_limit_stays_while_the_base_s_pose_is_unknown(policy: SafetyPolicy) -> None:
    clock = Clock(100.0)
    gate = SafetyGate(policy, EstopLatch(TOKEN), clock, Clock(WALL))
    store = FakeStore(zones=[zone()])
    gate.set_incidents(store)
    at(gate, clock, Pose2D(x=ZONE_X, y=ZONE_Y)).tick()
    assert gate.separation.scale == 0.5
    # Odometry stops (nobody near, reports keep coming): the base is still where it was last seen.
    clock.now += gate.policy.policy.monitor.state_max_age + TICK
    gate.humans(PerceivedHumans(stamp=0.0, humans=[]))
    gate.tick()
    assert gate.separation.scale == 0.5, gate.separation.reason
    assert gate.separation.reason.startswith("caution zone")
    # Once the operator clears the zone, its limit is gone, pose known or not.
    store.set_zones([])
    gate.humans(PerceivedHumans(stamp=0.0, humans=[]))
    gate.tick()
    assert gate.separation.scale == 1.0, gate.separation.reason


# The e-stop and mode state files: a FIFO in their place


def _load_within(load: Callable[[], object], fifo: Path) -> object:
    """`load()` on a thread, given a deadline; a reader stuck on the FIFO is let go by opening its
    other end, so the test ends either way."""
    done: list[object] = []
    reader = threading.Thread(target=lambda: done.append(load()), daemon=True)
    reader.start()
    reader.join(DEADLINE)
    if reader.is_alive():
        with fifo.open("wb"):
            pass
        reader.join(DEADLINE)
        pytest.fail(f"reading {fifo.name} did not return within {DEADLINE:g} s: a FIFO hung it")
    return done[0]


def test_a_fifo_as_the_estop_state_file_starts_latched_instead_of_hanging(tmp_path: Path) -> None:
    fifo = tmp_path / "estop.json"
    os.mkfifo(fifo)
    latch = _load_within(lambda: EstopLatch(TOKEN, fifo), fifo)
    assert isinstance(latch, EstopLatch)
    assert latch.state.latched and "unreadable" in latch.state.reason


def test_a_fifo_as_the_mode_state_file_starts_supervised_instead_of_hanging(tmp_path: Path) -> None:
    fifo = tmp_path / "mode.json"
    os.mkfifo(fifo)
    modes = _load_within(lambda: ModeFile(fifo), fifo)
    assert isinstance(modes, ModeFile)
    assert modes.mode is ControlMode.SUPERVISED
