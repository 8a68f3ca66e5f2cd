"""Safety's incident memory against files it did not write as it writes them (hand-made, damaged,
hostile) and `tether incidents` against answers it cannot show as dates: one bad row costs that row's
bad values, never the memory, the zones or the listing."""

from __future__ import annotations

import os
import sqlite3
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec
import pytest

from schemas.incidents import ForgetAction, Incident, IncidentKind, IncidentList, IncidentQuery
from services.safety import incidents
from services.safety.incidents import IncidentStore
from tether.incidentscli import incident_json, parse_since, timeline_rows


@pytest.fixture
def path(tmp_path: Path) -> Iterator[Path]:
    """A store file with three collisions at (1, 1): a caution zone (3 within 1 m)."""
    file = tmp_path / "incidents.sqlite"
    store = IncidentStore(file)
    for i in range(3):
        store.add(IncidentKind.COLLISION, f"bumped {i}", x=1.0, y=1.0 + 0.1 * i)
    store.close()
    yield file


def edit(path: Path, *statements: str) -> None:
    db = sqlite3.connect(path)
    try:
        for statement in statements:
            db.execute(statement)
        db.commit()
    finally:
        db.close()


def opened(path: Path) -> IncidentStore:
    store = IncidentStore(path)
    store.refresh_zones(3, 1.0, 0.5)
    return store


def test_values_the_wire_refuses_are_left_out_and_every_answer_still_decodes(path: Path) -> None:
    edit(
        path,
        "INSERT INTO incidents (id, stamp, kind, reason, x, y, yaw, hand_x, hand_y, hand_z, objects, people)"
        f" VALUES (9, 1000.0, 'dropped', 'forged', 5000.0, 2.0, 1e6, 1.0, 1.0, -1e9, '[\"\", \"{'a' * 500}\"]',"
        " '[\"bob\", 7]')",
    )
    store = opened(path)
    try:
        answer = store.query(IncidentQuery())
        # What safety/incidents replies, as the agent and `tether incidents` decode it.
        decoded = msgspec.json.decode(msgspec.json.encode(answer), type=IncidentList)
        forged = next(i for i in decoded.incidents if i.id == 9)
        assert (forged.x, forged.y, forged.yaw, forged.hand) == (None, None, None, None)
        assert forged.objects == ["a" * 200] and forged.people == ["bob", "7"]
        assert len(decoded.zones) == 1 and decoded.zones[0].count == 3
    finally:
        store.close()


def test_text_that_is_not_utf8_costs_that_text_not_the_memory_or_its_zone(path: Path) -> None:
    edit(path, "UPDATE incidents SET reason = CAST(X'FF41' AS TEXT), source = CAST(X'C0' AS TEXT) WHERE id = 2")
    store = opened(path)
    try:
        assert store.fault == "" and store.size == 3
        assert len(store.caution_zones().zones) == 1
        damaged = store.query(IncidentQuery(id=2)).incidents[0]
        assert damaged.reason == "\ufffdA"
        new = store.add(IncidentKind.DROPPED, "still written", x=1.0, y=1.0)
        assert store.fault == "" and store.pending == 0 and new.id == 4
    finally:
        store.close()


def test_a_cleared_mark_that_is_not_a_number_does_not_clear(path: Path) -> None:
    edit(path, "UPDATE incidents SET cleared = 'no' WHERE id = 1")
    store = opened(path)
    try:
        assert len(store.caution_zones().zones) == 1
    finally:
        store.close()


def test_rows_sharing_a_number_are_held_once_and_forgetting_it_lists_it_no_more(tmp_path: Path) -> None:
    file = tmp_path / "incidents.sqlite"
    db = sqlite3.connect(file)
    # The layout safety writes, but `id` not the key: a file made by hand.
    db.executescript(incidents._SCHEMA.replace("id INTEGER PRIMARY KEY", "id INTEGER") + "PRAGMA user_version = 1;")
    db.executemany(
        "INSERT INTO incidents (id, stamp, kind, x, y) VALUES (7, ?, 'collision', 1.0, 1.0)",
        [(1000.0 + k,) for k in range(3)],
    )
    db.commit()
    db.close()
    store = opened(file)
    try:
        assert [i.id for i in store.query(IncidentQuery()).incidents] == [7]
        assert store.forget(7, ForgetAction.FORGET, "op", "a duplicate", 1.0) == [7]
        assert store.query(IncidentQuery()).incidents == [] and store.near([(1.0, 1.0)], 1.0) == []
        new = store.add(IncidentKind.DROPPED, "after", x=1.0, y=1.0)
        assert [i.id for i in store.query(IncidentQuery()).incidents] == [new.id]
    finally:
        store.close()


@pytest.mark.parametrize("stamp", [1e20, -1e20, 1e12])
def test_the_cli_lists_an_incident_whose_time_is_no_date(stamp: float) -> None:
    data = incident_json(Incident(id=1, stamp=stamp, kind=IncidentKind.COLLISION))
    assert data["time"] is None and data["stamp"] == stamp


def test_since_a_date_out_of_range_is_refused_naming_the_option() -> None:
    with pytest.raises(ValueError, match="--since '0001-01-01'"):
        parse_since("0001-01-01", 1_800_000_000.0)


def test_new_incidents_where_thousands_are_cost_no_more_than_computing_the_zones_afresh(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A flood of reports at one place: updating the zones around each new incident there goes through
    every incident there, once for each, and the writer falls behind (its queue full, a later e-stop
    is dropped). A batch of them costs one computation afresh at most."""
    file = tmp_path / "incidents.sqlite"
    flood = (Incident(id=i, stamp=1000.0 + i, kind=IncidentKind.GRASP_FAILED, x=1.0, y=1.0) for i in range(1, 5001))
    incidents.seed(file, flood)
    store = opened(file)
    try:
        for _ in range(20):
            store.add(IncidentKind.GRASP_FAILED, "again", x=1.0, y=1.0)
        looked_at: list[int] = []
        zone = incidents._zone

        def counted(members: list[incidents.Point], radius: float, speed_scale: float) -> Any:
            looked_at.append(len(members))
            return zone(members, radius, speed_scale)

        monkeypatch.setattr(incidents, "_zone", counted)
        (only,) = store.refresh_zones(3, 1.0, 0.5).zones
        assert only.count == 5020
        assert sum(looked_at) <= 2 * store.size, f"{len(looked_at)} zones computed, over {sum(looked_at)} incidents"
    finally:
        store.close()


def unreadable(tmp_path: Path) -> Path:
    """A file that exists, is not empty and cannot be opened for reading by this process."""
    if os.geteuid() != 0:
        locked = tmp_path / "locked.mcap"
        locked.write_bytes(b"\x89MCAP0\r\n" + b"\0" * 64)
        locked.chmod(0)
        return locked
    write_only = Path("/sys/bus/pci/rescan")  # refused to root too
    if not write_only.is_file():
        pytest.skip("no file here that root cannot read")
    return write_only


def test_show_notes_a_recording_it_cannot_open(tmp_path: Path) -> None:
    path = unreadable(tmp_path)
    rows, note = timeline_rows(path, 1_800_000_000.0, 10.0)
    assert rows == [] and note == f"the recording cannot be read: cannot read recording {path}: Permission denied"
