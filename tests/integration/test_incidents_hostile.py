"""Safety started on an incident store it did not write as it writes them (a row edited by hand or by
an attacker: text that is not UTF-8, a place off the map, a time no date can show): the incidents
and the caution zone they make are still in force, `safety/incidents` still answers in a form its
callers decode, and `tether incidents` lists and shows them."""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Iterator
from pathlib import Path

import pytest

from schemas import keys
from schemas.incidents import Incident, IncidentKind, IncidentList, IncidentQuery
from services.safety.incidents import seed
from tests.integration.conftest import Stack, start_stack, stop_stack, tether_cli

FORGED = 4


def hostile_store(path: Path) -> None:
    """Three collisions at (1, 1), a caution zone; a fourth row with a reason that is not UTF-8, a
    place 5 km away and a stamp beyond any date."""
    seed(path, (Incident(id=i, stamp=1.7e9 + i, kind=IncidentKind.COLLISION, x=1.0, y=1.0) for i in (1, 2, 3)))
    db = sqlite3.connect(path)
    try:
        db.execute(
            "INSERT INTO incidents (id, stamp, kind, reason, x, y) "
            "VALUES (?, 1e20, 'dropped', CAST(X'FF1B5B326A' AS TEXT), 5000.0, 1.0)",
            (FORGED,),
        )
        db.commit()
    finally:
        db.close()


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    tmp = tmp_path_factory.mktemp("hostile-incidents")
    store = tmp / "incidents.sqlite"
    hostile_store(store)
    s = start_stack(tmp, realtime_factor=1.0, services=("safety",), safety_options=f'incident_store = "{store}"\n')
    try:
        yield s
    finally:
        stop_stack(s)


def test_a_hostile_row_costs_its_bad_values_not_the_memory_the_zone_or_the_answer(stack: Stack) -> None:
    answer: IncidentList = stack.node.call(keys.INCIDENTS, IncidentQuery(), timeout=5.0)
    assert answer.store == "", answer.store
    assert sorted(i.id for i in answer.incidents) == [1, 2, 3, FORGED]
    (zone,) = answer.zones
    assert zone.count == 3 and zone.incidents == [1, 2, 3]
    forged = next(i for i in answer.incidents if i.id == FORGED)
    assert (forged.x, forged.y) == (None, None) and forged.reason == "\ufffd\x1b[2j"


def test_the_cli_lists_and_shows_them_with_the_escape_made_harmless(stack: Stack) -> None:
    listed = tether_cli(stack, "incidents", "--json")
    assert listed.returncode == 0, listed.stderr
    rows = {r["id"]: r for r in json.loads(listed.stdout)["incidents"]}
    assert rows[FORGED]["time"] is None and rows[FORGED]["stamp"] == 1e20 and rows[1]["time"]
    table = tether_cli(stack, "incidents")
    assert table.returncode == 0, table.stderr
    assert "\x1b" not in table.stdout and "caution zone: 3 incidents" in table.stdout, table.stdout
    shown = tether_cli(stack, "incidents", "show", str(FORGED))
    assert shown.returncode == 0, shown.stderr
    assert "stamp 1e+20 is no date" in shown.stdout and "\x1b" not in shown.stdout, shown.stdout
