"""Safety's incident store on real SQLite files: what it lists, near, the caution zones, forgetting and
clearing, and the files it must survive (newer, corrupt, locked, huge); and the watch that decides
which decisions are incidents."""

from __future__ import annotations

import random
import sqlite3
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from schemas import keys
from schemas.actions import Feedback, GoalState, GoalStatus
from schemas.common import Stage, Vec3
from schemas.executor import ExecutePlanFeedback
from schemas.incidents import CautionZone, ForgetAction, IncidentKind, IncidentQuery, IncidentReport
from schemas.safety import Decision, EstopState, Rule
from services.safety.gate import GateEvent
from services.safety.incidents import (
    _INSERT,
    MAX_PENDING,
    REPORT_PERIOD,
    RETRY_INTERVAL,
    IncidentStore,
    IncidentStoreError,
    IncidentWatch,
    _cluster,
)
from services.safety.monitor import Separation


class Clock:
    def __init__(self, t: float = 1_000_000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        self.t += 1.0
        return self.t


class Steady:
    """The store's monotonic clock, moved only by the test: when a file with a fault is tried again."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t

    def retry(self) -> None:
        self.t += RETRY_INTERVAL


def zones(store: IncidentStore) -> list[CautionZone]:
    """The zones as the writer's thread computes them (3 incidents within 1 m, half speed)."""
    return list(store.refresh_zones(3, 1.0, 0.5).zones)


@pytest.fixture
def store(tmp_path: Path) -> Iterator[IncidentStore]:
    s = IncidentStore(tmp_path / "incidents.sqlite", clock=Clock())
    yield s
    s.close()


def test_incidents_are_listed_newest_first_with_every_field_and_survive_reopening(tmp_path: Path) -> None:
    path = tmp_path / "state" / "incidents-r1.sqlite"
    clock = Clock()
    store = IncidentStore(path, clock=clock)
    assert store.fault == ""
    first = store.add(
        IncidentKind.ESTOP,
        "person in the way",
        x=2.1,
        y=3.0,
        yaw=0.5,
        hand=Vec3(x=2.5, y=3.0, z=0.8),
        source="operator",
        rule="estop",
        goal_id="g1",
        step=2,
        label="3",
        objects=["red cup"],
        people=["alice"],
        recording="/rec/a.mcap",
    )
    second = store.add(IncidentKind.DROPPED, "the cup slipped", objects=["red cup"])
    assert (first.id, second.id) == (1, 2)
    store.close()
    again = IncidentStore(path, clock=clock)
    listed = again.query(IncidentQuery())
    assert [i.id for i in listed.incidents] == [2, 1] and listed.total == 2 and listed.store == ""
    assert listed.incidents[1] == first
    assert again.add(IncidentKind.VETO, "v").id == 3
    assert again.query(IncidentQuery(kinds=[IncidentKind.DROPPED])).incidents == [second]
    near = again.query(IncidentQuery(x=2.0, y=3.0, radius=0.5))
    assert [i.id for i in near.incidents] == [1] and near.total == 1
    assert again.query(IncidentQuery(since=first.stamp + 0.5)).total == 2
    assert again.query(IncidentQuery(id=1)).incidents == [first]
    limited = again.query(IncidentQuery(limit=1))
    assert len(limited.incidents) == 1 and limited.total == 3
    again.close()


def test_near_finds_incidents_along_points_newest_first_once_each(store: IncidentStore) -> None:
    a = store.add(IncidentKind.ESTOP, "a", x=1.0, y=1.0)
    store.add(IncidentKind.VETO, "far", x=5.0, y=5.0)
    c = store.add(IncidentKind.NEAR_MISS, "c", x=2.9, y=1.0)
    store.add(IncidentKind.COLLISION, "nowhere")
    found = store.near([(1.0, 1.2), (1.5, 1.0), (3.0, 1.0)], 0.5)
    assert [i.id for i in found] == [c.id, a.id]
    assert store.near([(1.0, 1.0)], 0.5, limit=1) == [a]
    assert store.near([(10.0, 10.0)], 2.0) == []
    # Just outside the radius, in the same cell.
    assert store.near([(1.0, 1.51)], 0.5) == []


def test_repeated_incidents_make_a_zone_until_cleared_and_forgotten_ones_never_count(store: IncidentStore) -> None:
    ids = [store.add(IncidentKind.NEAR_MISS, "door", x=3.0 + 0.1 * i, y=1.0).id for i in range(3)]
    store.add(IncidentKind.NEAR_MISS, "elsewhere", x=8.0, y=1.0)
    v0 = store.version
    assert store.caution_zones().zones == (), "nothing computed yet: a reader never computes them"
    (zone,) = zones(store)
    assert zone.incidents == ids and zone.count == 3 and zone.speed_scale == 0.5
    assert zone.x == pytest.approx(3.1) and zone.radius >= 1.0 and zone.kinds == [IncidentKind.NEAR_MISS]
    assert store.refresh_zones(3, 1.0, 0.5) is store.caution_zones()  # unchanged: not computed again
    assert store.query(IncidentQuery()).zones == [zone]
    # Forgetting one breaks the zone; it is no longer listed nor found near.
    assert store.forget(ids[0], ForgetAction.FORGET, "op", "a test", 1.0) == [ids[0]]
    assert store.version > v0
    assert zones(store) == []
    assert ids[0] not in [i.id for i in store.query(IncidentQuery()).incidents]
    assert ids[0] not in [i.id for i in store.near([(3.0, 1.0)], 1.0)]
    with pytest.raises(KeyError, match="already forgotten"):
        store.forget(ids[0], ForgetAction.FORGET, "op", "again", 1.0)
    with pytest.raises(KeyError, match="no incident 99"):
        store.forget(99, ForgetAction.FORGET, "op", "unknown", 1.0)
    # A fourth makes it again; clearing takes the whole zone: they still warn, they no longer count.
    store.add(IncidentKind.ESTOP, "door again", x=3.15, y=1.05)
    (zone,) = zones(store)
    cleared = store.forget(zone.incidents[0], ForgetAction.CLEAR, "op", "door widened", 1.0)
    assert cleared == zone.incidents
    assert zones(store) == []
    warned = store.near([(3.1, 1.0)], 0.5)
    assert {i.id for i in warned} == set(zone.incidents) and all(i.cleared for i in warned)


def test_a_store_written_by_a_newer_version_is_left_untouched(tmp_path: Path) -> None:
    path = tmp_path / "incidents.sqlite"
    db = sqlite3.connect(path)
    db.execute("CREATE TABLE future (a)")
    db.execute("PRAGMA user_version = 7")
    db.commit()
    db.close()
    before = path.read_bytes()
    store = IncidentStore(path)
    assert "newer version" in store.fault and str(path) in store.fault and "schema 7" in store.fault
    kept = store.add(IncidentKind.ESTOP, "kept in memory", x=1.0, y=1.0)
    assert store.query(IncidentQuery()).incidents == [kept]
    assert store.query(IncidentQuery()).store == store.fault
    assert store.near([(1.0, 1.0)], 0.5) == [kept]
    with pytest.raises(IncidentStoreError, match="newer version"):
        store.forget(kept.id, ForgetAction.FORGET, "op", "x", 1.0)
    store.close()
    assert path.read_bytes() == before


def test_a_corrupt_file_is_a_fault_incidents_are_kept_in_memory_and_written_once_it_is_replaced(
    tmp_path: Path,
) -> None:
    path = tmp_path / "incidents.sqlite"
    path.write_bytes(b"this is not a database at all " * 100)
    steady = Steady()
    store = IncidentStore(path, monotonic=steady)
    assert str(path) in store.fault and "not a database" in store.fault
    kept = [store.add(IncidentKind.NEAR_MISS, f"n{i}", x=1.0, y=1.0 + 0.1 * i) for i in range(3)]
    assert store.fault and len(zones(store)) == 1  # they still count
    assert store.query(IncidentQuery()).total == 3
    path.unlink()  # an operator moves the broken file away
    store.add(IncidentKind.ESTOP, "after", x=1.0, y=1.0)
    assert store.fault and not path.exists(), "tried again only after RETRY_INTERVAL, not at every incident"
    steady.retry()
    assert store.flush() and store.fault == "" and store.pending == 0
    store.close()
    again = IncidentStore(path)
    assert [i.reason for i in again.query(IncidentQuery()).incidents] == ["after", *(k.reason for k in reversed(kept))]
    again.close()


def test_at_most_max_pending_incidents_wait_in_memory(tmp_path: Path) -> None:
    path = tmp_path / "incidents.sqlite"
    path.write_bytes(b"garbage" * 1000)
    store = IncidentStore(path)
    for i in range(MAX_PENDING + 5):
        store.add(IncidentKind.VETO, f"v{i}", x=float(i % 10), y=0.0)
    listed = store.query(IncidentQuery(limit=1000))
    assert listed.total == MAX_PENDING and listed.incidents[-1].reason == "v5"


def test_a_locked_file_is_a_fault_and_the_kept_incidents_are_written_once_it_is_released(tmp_path: Path) -> None:
    path = tmp_path / "incidents.sqlite"
    steady = Steady()
    store = IncidentStore(path, monotonic=steady)
    first = store.add(IncidentKind.ESTOP, "before", x=0.0, y=0.0)
    other = sqlite3.connect(path, isolation_level=None)
    other.execute("BEGIN EXCLUSIVE")
    try:
        kept = store.add(IncidentKind.VETO, "while locked", x=0.0, y=0.1)
        assert "locked" in store.fault and str(path) in store.fault
        assert kept.id == first.id + 1
        # Still near, still listed (from memory), and forgetting waits for the file.
        assert [i.id for i in store.near([(0.0, 0.0)], 0.5)] == [kept.id, first.id]
        listed = store.query(IncidentQuery())
        assert kept in listed.incidents and first in listed.incidents and "locked" in listed.store
        with pytest.raises(IncidentStoreError, match="locked"):
            store.forget(first.id, ForgetAction.FORGET, "op", "x", 1.0)
    finally:
        other.execute("ROLLBACK")
        other.close()
    store.add(IncidentKind.VETO, "after", x=0.0, y=0.2)
    assert "locked" in store.fault, "not tried again before RETRY_INTERVAL"
    steady.retry()
    assert store.flush() and store.fault == ""
    store.close()
    again = IncidentStore(path)
    assert [i.reason for i in again.query(IncidentQuery()).incidents] == ["after", "while locked", "before"]
    again.close()


def test_the_fault_stays_until_the_incidents_kept_in_memory_are_in_the_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A store listed without a fault has its incidents in the file: the fault goes once what waited in
    memory is written, not when the file opens again (a test that read the file as soon as the fault
    went found the kept incident missing)."""
    path = tmp_path / "incidents.sqlite"
    steady = Steady()
    store = IncidentStore(path, monotonic=steady)
    other = sqlite3.connect(path, isolation_level=None)
    other.execute("BEGIN EXCLUSIVE")
    try:
        store.add(IncidentKind.VETO, "while locked", x=0.0, y=0.1)
    finally:
        other.execute("ROLLBACK")
        other.close()
    assert "locked" in store.fault
    # What a listing says while the kept incident is written: the store's own (real) connection
    # reports each statement it runs.
    listed_while_writing: list[str] = []
    connect = sqlite3.connect

    def traced(*args: Any, **kwargs: Any) -> sqlite3.Connection:
        db = connect(*args, **kwargs)

        def statement(sql: str) -> None:
            if sql.lstrip().upper().startswith("INSERT"):
                listed_while_writing.append(store.query(IncidentQuery()).store)

        db.set_trace_callback(statement)
        return db

    monkeypatch.setattr(sqlite3, "connect", traced)
    steady.retry()
    assert store.flush()
    assert listed_while_writing, "the kept incident was not written"
    assert all("locked" in fault for fault in listed_while_writing), listed_while_writing
    assert store.query(IncidentQuery()).store == ""
    store.close()


def test_an_incident_numbered_while_the_file_was_unreadable_gets_a_free_number(tmp_path: Path) -> None:
    path = tmp_path / "incidents.sqlite"
    good = IncidentStore(path)
    for i in range(3):
        good.add(IncidentKind.VETO, f"old {i}")
    good.close()
    saved = path.read_bytes()
    path.write_bytes(b"garbage" * 1000)
    steady = Steady()
    store = IncidentStore(path, monotonic=steady)
    kept = store.add(IncidentKind.ESTOP, "kept", x=1.0, y=1.0)
    assert kept.id == 1 and store.fault
    path.write_bytes(saved)  # the good file is back
    steady.retry()
    after = store.add(IncidentKind.ESTOP, "after")
    assert store.fault == ""
    listed = store.query(IncidentQuery())
    assert [i.reason for i in listed.incidents] == ["after", "kept", "old 2", "old 1", "old 0"]
    assert len({i.id for i in listed.incidents}) == 5 and after.id == 5
    assert [i.reason for i in store.near([(1.0, 1.0)], 0.1)] == ["kept"]
    store.close()


def test_near_and_zones_over_100k_incidents(tmp_path: Path) -> None:
    path = tmp_path / "incidents.sqlite"
    IncidentStore(path).close()
    rng = random.Random(19)
    rows = []
    for i in range(1, 100_001):
        x, y = rng.uniform(0.0, 20.0), rng.uniform(0.0, 20.0)
        rows.append((i, 1e9 + i, "veto", "r", x, y, 0.0, None, None, None, "", "", "", None, "", "[]", "[]", "", 0))
    db = sqlite3.connect(path)
    db.executemany(_INSERT, rows)
    db.commit()
    db.close()
    store = IncidentStore(path)
    assert store.fault == ""
    for px, py in [(rng.uniform(0.0, 20.0), rng.uniform(0.0, 20.0)) for _ in range(5)]:
        want = sorted(
            (r for r in rows if (r[4] - px) ** 2 + (r[5] - py) ** 2 <= 0.3**2), key=lambda r: r[1], reverse=True
        )[:20]
        assert [i.id for i in store.near([(px, py)], 0.3)] == [r[0] for r in want]
    found = zones(store)
    assert found and all(z.count >= 3 for z in found)
    store.close()


# The watch: which decisions are incidents


class Mono:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def running(watch: IncidentWatch, goal: str = "plan1") -> None:
    watch.plan_status(GoalStatus(goal_id=goal, state=GoalState.EXECUTING))
    feedback = ExecutePlanFeedback(stage=Stage.EXECUTE, step=1, label="2")
    watch.plan_feedback(Feedback(goal_id=goal, feedback=feedback))


def test_the_watch_names_estops_by_their_source_and_groups_vetoes_of_a_running_plan() -> None:
    clock = Mono()
    watch = IncidentWatch(0.15, clock)
    latched = GateEvent(keys.ESTOP.path, Decision.LATCHED, "by monitor: too fast", rule=Rule.MONITOR_SPEED)
    (trip,) = watch.decided([latched], EstopState(latched=True, source="monitor", reason="too fast"))
    assert (trip.kind, trip.source, trip.rule) == (IncidentKind.MONITOR, "monitor", "monitor_speed")
    (estop,) = watch.decided([latched], EstopState(latched=True, source="operator"))
    assert estop.kind is IncidentKind.ESTOP
    veto = GateEvent(keys.CMD_NAVIGATE.send_goal.path, Decision.VETOED, "keep out", rule=Rule.KEEP_OUT)
    assert watch.decided([veto], EstopState(latched=False)) == []  # no plan runs
    running(watch)
    assert watch.context() == ("plan1", 1, "2")
    (first,) = watch.decided([veto], EstopState(latched=False))
    assert first.kind is IncidentKind.VETO and first.rule == "keep_out"
    clock.t += 4.0
    assert watch.decided([veto], EstopState(latched=False)) == []
    latched_veto = GateEvent(keys.CMD_VEL.path, Decision.VETOED, "e-stop", rule=Rule.ESTOP)
    mode_veto = GateEvent(keys.CMD_GRIPPER.send_goal.path, Decision.VETOED, "mode direct", rule=Rule.MODE)
    teleop = GateEvent(keys.TELEOP_CMD_VEL.path, Decision.VETOED, "zone", rule=Rule.KEEP_OUT)
    assert watch.decided([latched_veto, mode_veto, teleop], EstopState(latched=True)) == []
    (speed,) = watch.decided(
        [GateEvent(keys.CMD_VEL.path, Decision.VETOED, "fast", rule=Rule.BASE_SPEED)], EstopState(latched=False)
    )
    assert speed.source == keys.CMD_VEL.path
    clock.t += 5.0
    assert len(watch.decided([veto], EstopState(latched=False))) == 1
    watch.plan_status(GoalStatus(goal_id="plan1", state=GoalState.SUCCEEDED))
    assert watch.context() == ("", None, "")


def test_a_refusal_for_the_other_motion_is_no_incident() -> None:
    """Two motions asked at once say nothing of the place: such a refusal while a plan ran was a veto
    incident, counting towards a caution zone there."""
    watch = IncidentWatch(0.15, Mono())
    running(watch)
    both = GateEvent(keys.CMD_TRAJECTORY.send_goal.path, Decision.VETOED, "a navigation runs", rule=Rule.ONE_MOTION)
    assert watch.decided([both], EstopState(latched=False)) == []


def test_a_pause_closer_than_the_near_miss_distance_while_under_way_is_one_near_miss() -> None:
    clock = Mono()
    watch = IncidentWatch(0.15, clock)
    close = Separation(0.0, "bob is 0.10 m away", 0.10, "bob")
    assert watch.separation(close) is None  # parked, no plan: a person passing is no near-miss
    watch.base_moved(True)
    (draft,) = [watch.separation(close)]
    assert draft is not None and draft.kind is IncidentKind.NEAR_MISS and draft.people == ("bob",)
    assert watch.separation(close) is None  # one per pause
    assert watch.separation(Separation(0.5, "", 0.4, "bob")) is None
    assert watch.separation(Separation(0.0, "", 0.2, "bob")) is None  # paused, but not that close
    assert watch.separation(close) is not None


def test_only_reported_kinds_are_taken_and_at_a_bounded_rate() -> None:
    clock = Mono()
    watch = IncidentWatch(0.15, clock)
    refused = watch.report(IncidentReport(kind=IncidentKind.ESTOP, reason="pretend"))
    assert isinstance(refused, str) and "only" in refused
    running(watch, "p7")
    taken = watch.report(IncidentReport(kind=IncidentKind.DROPPED, reason="slipped", objects=["red cup"]))
    assert not isinstance(taken, str) and (taken.goal_id, taken.step, taken.objects) == ("p7", 1, ("red cup",))
    results = [watch.report(IncidentReport(kind=IncidentKind.COLLISION, reason="bump")) for _ in range(100)]
    assert sum(not isinstance(r, str) for r in results) < 25
    clock.t += REPORT_PERIOD
    assert not isinstance(watch.report(IncidentReport(kind=IncidentKind.COLLISION, reason="later")), str)
    # A reporter looping at 20 a second for a minute: what a robot sees in an hour at most, not 1,200
    # incidents (each up to 5 KB, kept for good).
    taken = 0
    for _ in range(20 * 60):
        clock.t += 0.05
        taken += not isinstance(watch.report(IncidentReport(kind=IncidentKind.COLLISION, reason="loop")), str)
    assert taken <= 60 / REPORT_PERIOD + 1, taken


def test_a_place_with_a_thousand_incidents_is_one_zone_and_near_gives_the_newest(tmp_path: Path) -> None:
    path = tmp_path / "incidents.sqlite"
    IncidentStore(path).close()
    db = sqlite3.connect(path)
    row = ("estop", "", 1.0, 1.0, None, None, None, None, "", "", "", None, "", "[]", "[]", "", 0)
    db.executemany(_INSERT, [(i, float(i), *row) for i in range(1, 1001)])
    db.commit()
    db.close()
    store = IncidentStore(path)
    assert [i.id for i in store.near([(1.0, 1.0)], 0.1, limit=3)] == [1000, 999, 998]
    (zone,) = zones(store)
    assert zone.count == 1000 and zone.kinds == [IncidentKind.ESTOP]
    store.close()


# Readers never wait for the file; the zones are the writer's, updated around a new incident


STUCK = 60.0  # the busy timeout of a store whose writer must stay stuck on a locked file for the test
DEADLINE = 20.0  # generous: what must not wait for the writer finishes long before STUCK


def stuck_writer(store: IncidentStore, path: Path, x: float, y: float) -> tuple[sqlite3.Connection, threading.Thread]:
    """Another connection holds the file locked and the store's writer adds an incident at (x, y): it
    is in memory, and the writer waits for the file (up to STUCK seconds) holding the store's file lock."""
    other = sqlite3.connect(path, isolation_level=None)
    other.execute("BEGIN EXCLUSIVE")
    version = store.version
    writer = threading.Thread(target=store.add, args=(IncidentKind.VETO, "while locked"), kwargs={"x": x, "y": y})
    writer.start()
    deadline = time.monotonic() + DEADLINE
    while store.version == version and time.monotonic() < deadline:
        time.sleep(0.001)
    assert store.version > version, "the writer never put the incident in memory"
    return other, writer


def test_near_query_version_and_the_zones_never_wait_for_a_writer_stuck_on_a_locked_file(tmp_path: Path) -> None:
    path = tmp_path / "incidents.sqlite"
    store = IncidentStore(path, clock=Clock(), busy_timeout=STUCK)
    ids = [store.add(IncidentKind.NEAR_MISS, "door", x=3.0 + 0.1 * i, y=1.0).id for i in range(3)]
    (zone,) = zones(store)
    other, writer = stuck_writer(store, path, 3.05, 1.0)
    answered: dict[str, Any] = {}
    done = threading.Event()

    def read() -> None:
        answered["version"] = store.version
        answered["near"] = [i.id for i in store.near([(3.0, 1.0)], 0.5)]
        answered["query"] = store.query(IncidentQuery(x=3.0, y=1.0))
        answered["zones"] = store.caution_zones()
        done.set()

    try:
        threading.Thread(target=read, daemon=True).start()
        assert done.wait(DEADLINE), "a reader waited for the writer"
        assert writer.is_alive() and not store._db_lock.acquire(blocking=False), "the writer was stuck all along"
    finally:
        other.execute("ROLLBACK")
        other.close()
        writer.join(DEADLINE)
    new = ids[-1] + 1
    assert answered["near"] == [new, *reversed(ids)], "the new incident is near at once, from memory"
    assert [i.id for i in answered["query"].incidents] == [new, *reversed(ids)] and answered["query"].store == ""
    assert answered["zones"].zones == (zone,), "the zones in force until the writer computes them again"
    assert zones(store)[0].incidents == [*ids, new]
    assert not writer.is_alive() and store.fault == "" and store.pending == 0
    store.close()


def test_a_new_incident_updates_the_zones_exactly_as_computing_them_afresh(tmp_path: Path) -> None:
    """Incidents dense and sparse, one at a time (zones joined, made, and new zones that change later
    ones, which are computed afresh), a clear and a forget among them: the zones are always the same
    as clustering all the incidents from nothing gives."""
    rng = random.Random(7)
    store = IncidentStore(tmp_path / "incidents.sqlite", clock=Clock())
    params = (4, 0.6, 0.5)
    for n in range(150):
        x, y = rng.gauss(5.0, 1.0), rng.gauss(5.0, 1.0)
        incident = store.add(rng.choice(list(IncidentKind)), f"i{n}", x=x, y=y)
        if n == 70:
            store.forget(incident.id, ForgetAction.CLEAR, "op", "tidied", 0.5)
        elif n == 110:
            store.forget(incident.id - 3, ForgetAction.FORGET, "op", "never happened", 0.5)
        if n % 3 == 0 or n > 135:
            mine = store.refresh_zones(*params).zones
            points = [(s.id, s.x, s.y, s.stamp, s.kind) for s in store._spots.values() if not s.cleared]
            assert mine == _cluster(points, params).map.zones, f"after incident {n}"
    assert len(store.caution_zones()) > 5
    store.close()


def test_a_store_from_a_newer_version_is_read_only_and_its_incidents_still_count(tmp_path: Path) -> None:
    """A newer tether added a column and a kind: what this version knows of its incidents still makes
    zones and warnings; the file is never written (its bytes and its time unchanged)."""
    path = tmp_path / "incidents.sqlite"
    db = sqlite3.connect(path)
    db.execute(
        "CREATE TABLE incidents (id INTEGER PRIMARY KEY, stamp REAL, kind TEXT, reason TEXT, x REAL, y REAL, "
        "severity INTEGER, cleared INTEGER, forgotten INTEGER)"
    )
    rows = [(i, 1e9 + i, "near_miss", f"door {i}", 2.0 + 0.1 * i, 1.0, 3, 0, 0) for i in range(1, 4)]
    rows += [(4, 1e9 + 4, "landslide", "a kind from the future", 2.0, 1.0, 9, 0, 0)]
    rows += [(5, 1e9 + 5, "estop", "forgotten", 2.0, 1.0, 1, 0, 1), (6, 1e9 + 6, "veto", "far", 9.0, 9.0, 1, 0, 0)]
    db.executemany("INSERT INTO incidents VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)", rows)
    db.execute("PRAGMA user_version = 9")
    db.commit()
    db.close()
    before, mtime = path.read_bytes(), path.stat().st_mtime_ns
    store = IncidentStore(path, clock=Clock(2e9))
    assert "newer version" in store.fault and "schema 9" in store.fault and "read only" in store.fault
    (zone,) = zones(store)
    assert zone.incidents == [1, 2, 3]
    assert [i.id for i in store.near([(2.0, 1.0)], 0.5)] == [3, 2, 1]
    assert store.near([(2.0, 1.0)], 0.5)[0].reason == "door 3"
    kept = store.add(IncidentKind.ESTOP, "kept in memory", x=2.1, y=1.0)
    assert kept.id == 7 and store.pending == 1
    assert zones(store)[0].incidents == [1, 2, 3, 7]
    assert store.query(IncidentQuery()).total == 5 and store.query(IncidentQuery()).store == store.fault
    with pytest.raises(IncidentStoreError, match="newer version"):
        store.forget(1, ForgetAction.CLEAR, "op", "x", 1.0)
    store.close()
    assert path.read_bytes() == before and path.stat().st_mtime_ns == mtime


def test_a_file_replaced_while_safety_runs_keeps_the_zones_and_gets_the_incidents_it_lacks(tmp_path: Path) -> None:
    path = tmp_path / "incidents.sqlite"
    steady = Steady()
    store = IncidentStore(path, clock=Clock(), monotonic=steady)
    known = [store.add(IncidentKind.NEAR_MISS, f"door {i}", x=3.0 + 0.1 * i, y=1.0) for i in range(3)]
    (zone,) = zones(store)
    # The file goes bad (the store lets the connection go), and an empty one takes its place.
    path.write_bytes(b"garbage" * 100)
    store.add(IncidentKind.VETO, "while broken", x=8.0, y=8.0)
    assert store.fault
    path.unlink()
    steady.retry()
    assert store.flush() and store.fault == ""
    assert zones(store) == [zone], "the zone stays: only an operator clears it"
    assert store.near([(3.1, 1.0)], 0.5) == list(reversed(known))
    store.close()
    again = IncidentStore(path)
    assert {i.reason for i in again.query(IncidentQuery()).incidents} == {"door 0", "door 1", "door 2", "while broken"}
    assert zones(again) == [zone]
    again.close()
