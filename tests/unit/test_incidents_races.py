"""Safety's memory of incidents while the recording thread and an operator act on it at once: clearing
a caution zone takes the incidents recorded before it even if the zones were not computed with them
yet, what is answered once a forget or a clear has replied shows its effect, and a zone holding more
incidents than an answer lists is cleared with a reply the operator can read; and a store file whose
incident numbers are no numbers (not made by this code) costs those rows, never safety. Real SQLite
files; the node on the Recorder stand-in of test_safety_node."""

from __future__ import annotations

import sqlite3
import threading
from collections.abc import Iterator
from pathlib import Path

import msgspec
import pytest

from schemas import keys
from schemas.incidents import (
    MAX_LISTED,
    ForgetAction,
    ForgetIncident,
    ForgetReply,
    Incident,
    IncidentKind,
    IncidentList,
    IncidentQuery,
)
from schemas.trace import RecorderStatus
from services.safety import incidents
from services.safety.hazards import ZoneMap
from services.safety.incidents import Draft, IncidentStore, seed
from tests.unit.test_incident_store import Clock
from tests.unit.test_safety_node import Start, start  # noqa: F401  (the fixture)

COUNT, RADIUS, SCALE = 3, 1.0, 0.5
WAIT = 10.0


@pytest.fixture
def store(tmp_path: Path) -> Iterator[IncidentStore]:
    s = IncidentStore(tmp_path / "incidents.sqlite", clock=Clock())
    yield s
    s.close()


def refreshed(store: IncidentStore) -> list[tuple[float, float, int]]:
    return [(round(z.x, 3), round(z.y, 3), z.count) for z in store.refresh_zones(COUNT, RADIUS, SCALE).zones]


def near_miss(store: IncidentStore, x: float, y: float) -> int:
    return store.add(IncidentKind.NEAR_MISS, "person in the way", x=x, y=y).id


def test_clearing_a_zone_takes_incidents_recorded_before_the_zones_were_computed_again(store: IncidentStore) -> None:
    """The recording thread adds incidents and only then computes the zones: an operator's clear in
    between saw the zone without them, left them uncleared, and they made the zone again at once."""
    first = near_miss(store, 0.0, 0.0)  # the zone's oldest: it takes all within 1 m of it
    second = near_miss(store, 0.9, 0.0)
    near_miss(store, 0.45, 0.3)
    assert refreshed(store) != []
    # Within 1 m of the zone's oldest, 1.8 m from the one cleared: in the zone once it is computed.
    late = [near_miss(store, -0.9, 0.0), near_miss(store, -0.9, 0.1), near_miss(store, -0.8, -0.1)]
    cleared = store.forget(second, ForgetAction.CLEAR, "op", "door widened", RADIUS)
    assert first in cleared and set(late) <= set(cleared), "the zone's members recorded before the clear"
    assert refreshed(store) == [], "the zone cleared came back from the incidents it had not counted yet"


def test_a_query_after_a_clear_or_forget_shows_the_zones_without_them(store: IncidentStore) -> None:
    """What the store answers once forget returned: the cleared zone is gone from the zones listed and
    from those the gate reads, not only once the recording thread computes them again."""
    ids = [near_miss(store, 3.0 + 0.1 * i, 1.0) for i in range(3)]
    assert len(refreshed(store)) == 1
    store.forget(ids[1], ForgetAction.CLEAR, "op", "door widened", RADIUS)
    assert store.query(IncidentQuery()).zones == [] and store.caution_zones().zones == ()
    more = [near_miss(store, 8.0 + 0.1 * i, 1.0) for i in range(3)]
    assert len(refreshed(store)) == 1
    store.forget(more[0], ForgetAction.FORGET, "op", "a test", RADIUS)
    assert store.query(IncidentQuery()).zones == [] and store.caution_zones().zones == ()


def test_the_recording_thread_adding_to_a_zone_while_an_operator_clears_it(start: Start, tmp_path: Path) -> None:  # noqa: F811
    """The node: incidents recorded at a zone, the clear answered before the recording thread got to
    compute the zones with them. Once it has, no zone is left."""
    store = IncidentStore(tmp_path / "incidents.sqlite", clock=Clock())
    node, safety = start(incidents=store)
    rules = safety._incident_rules
    assert (rules.caution_count, rules.caution_radius) == (COUNT, RADIUS), "the policy's zones, as above"
    first = near_miss(store, 0.0, 0.0)
    second = near_miss(store, 0.9, 0.0)
    near_miss(store, 0.45, 0.3)
    safety._refresh_zones()
    assert len(store.caution_zones()) == 1
    # The recording thread is held at its next computing of the zones, after its incidents are in.
    real = store.refresh_zones
    held, go = threading.Event(), threading.Event()
    computed = threading.Condition()
    rounds = [0]

    def refresh(count: int, radius: float, speed_scale: float) -> ZoneMap:
        if threading.current_thread() is safety._incident_thread:
            held.set()
            assert go.wait(WAIT)
        zones = real(count, radius, speed_scale)
        if threading.current_thread() is safety._incident_thread:
            with computed:
                rounds[0] += 1
                computed.notify_all()
        return zones

    store.refresh_zones = refresh  # type: ignore[method-assign]
    # And at its first incident, asking the recorder's file name, until all three wait in its queue.
    asked, answer = threading.Event(), threading.Event()

    def recorder_status(_request: object) -> RecorderStatus:
        asked.set()
        assert answer.wait(WAIT)
        return RecorderStatus(path="", messages=0, started=0.0)

    node.answers[keys.RECORDER_STATUS.path] = recorder_status
    for x, y in [(-0.9, 0.0), (-0.9, 0.1), (-0.8, -0.1)]:
        safety._note(Draft(IncidentKind.NEAR_MISS, "person in the way", x=x, y=y))
    assert asked.wait(WAIT)
    answer.set()
    assert held.wait(WAIT), "the recording thread computes the zones after its incidents"
    assert store.size == 6, "recorded, not yet in the zones"
    forget = node.callbacks[keys.FORGET_INCIDENT.path]
    reply = forget(
        ForgetIncident(operator="alice", token="token", id=second, reason="widened", action=ForgetAction.CLEAR)
    )
    assert reply.ok and first in reply.changed, reply
    go.set()
    with computed:
        assert computed.wait_for(lambda: rounds[0] >= 2, WAIT), "the batch's and the clear's"
    assert store.caution_zones().zones == (), "the zone came back from the incidents the clear missed"


def test_clearing_a_zone_of_more_incidents_than_a_reply_lists_answers_readably(start: Start, tmp_path: Path) -> None:  # noqa: F811
    """A zone of 1,001 incidents: the clear's reply named all of them, more than a ForgetReply holds,
    so the operator's tether could not decode it (and said safety was unreachable) though it was done."""
    path = tmp_path / "incidents.sqlite"
    many = MAX_LISTED + 1
    seed(path, (Incident(id=i, stamp=1e9 + i, kind=IncidentKind.NEAR_MISS, x=1.0, y=1.0) for i in range(1, many + 1)))
    store = IncidentStore(path)
    node, _safety = start(incidents=store)
    assert [z.count for z in store.caution_zones().zones] == [many]
    forget = node.callbacks[keys.FORGET_INCIDENT.path]
    reply = forget(
        ForgetIncident(operator="alice", token="token", id=1, reason="moved the shelf", action=ForgetAction.CLEAR)
    )
    assert reply.ok and f"({many} incidents)" in reply.message, reply.message
    decoded = msgspec.json.decode(msgspec.json.encode(reply), type=ForgetReply)  # as the tether decodes it
    assert decoded.ok and len(decoded.changed) == MAX_LISTED
    assert all(i.cleared for i in store.near([(1.0, 1.0)], 0.1, limit=10))


@pytest.mark.parametrize(
    ("column", "number"),
    [
        ("id INTEGER", "NULL"),
        ("id INTEGER", "'seven'"),
        ("id INTEGER", "1e300"),
        ("id INTEGER PRIMARY KEY", "9223372036854775807"),  # SQLite's largest: the next is none
    ],
)
def test_a_file_whose_incident_numbers_are_no_numbers_costs_those_rows_not_safety(
    tmp_path: Path, column: str, number: str
) -> None:
    """A file not made by this code (by hand, another program, a crashed writer's garbage): a text or
    NULL number stopped safety from starting (TypeError out of the store's constructor), one at or
    beyond SQLite's largest made every new incident fail to be written, and every forget with it."""
    path = tmp_path / "incidents.sqlite"
    db = sqlite3.connect(path)
    db.executescript(incidents._SCHEMA.replace("id INTEGER PRIMARY KEY", column) + "PRAGMA user_version = 1;")
    db.execute(f"INSERT INTO incidents (id, stamp, kind, x, y) VALUES ({number}, 1000.0, 'collision', 1.0, 1.0)")
    db.execute("INSERT INTO incidents (id, stamp, kind, x, y) VALUES (3, 1001.0, 'collision', 1.0, 1.0)")
    db.commit()
    db.close()
    store = IncidentStore(path, clock=Clock())
    try:
        assert store.fault == "" and [i.id for i in store.query(IncidentQuery()).incidents] == [3]
        new = store.add(IncidentKind.DROPPED, "the cup slipped", x=1.0, y=1.0)
        assert (store.fault, store.pending) == ("", 0) and new.id == 4, "written, numbered after the readable"
        assert store.forget(new.id, ForgetAction.FORGET, "op", "a test", RADIUS) == [new.id]
        answer = store.query(IncidentQuery())
        assert msgspec.json.decode(msgspec.json.encode(answer), type=IncidentList).incidents == answer.incidents
    finally:
        store.close()
    check = sqlite3.connect(path)
    try:
        assert check.execute("SELECT forgotten FROM incidents WHERE id = 4").fetchone() == (1,)
    finally:
        check.close()
