"""`tether incidents`' pure parts: --since, "ago", where the recording is found, the JSON shape."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pytest

from schemas.incidents import Incident, IncidentKind
from tether.incidentscli import find_recording, incident_json, parse_since

NOW = 1_800_000_000.0


@pytest.mark.parametrize(
    ("text", "expected"), [("90s", NOW - 90), ("30m", NOW - 1800), ("2h", NOW - 7200), ("7d", NOW - 7 * 86400)]
)
def test_since_durations_count_back_from_now(text: str, expected: float) -> None:
    assert parse_since(text, NOW) == pytest.approx(expected)


def test_since_reads_an_iso_date_in_local_time() -> None:
    expected = dt.datetime(2026, 11, 20, 14, 0).astimezone().timestamp()
    assert parse_since("2026-11-20T14:00", NOW) == pytest.approx(expected)


@pytest.mark.parametrize("text", ["2x", "-3h", "yesterday", "nanh", ""])
def test_since_refuses_what_it_cannot_read_naming_it(text: str) -> None:
    with pytest.raises(ValueError, match="neither a duration"):
        parse_since(text, NOW)


def test_the_recording_is_found_where_noted_or_by_name_under_the_search_folder(tmp_path: Path) -> None:
    noted = tmp_path / "robot" / "run.mcap"
    here = tmp_path / "copies"
    here.mkdir()
    incident = Incident(id=1, stamp=NOW, kind=IncidentKind.ESTOP, recording=str(noted))
    assert find_recording(incident, None, here) is None
    (here / "run.mcap").write_bytes(b"")
    assert find_recording(incident, None, here) == here / "run.mcap"
    noted.parent.mkdir()
    noted.write_bytes(b"")
    assert find_recording(incident, None, here) == noted
    given = tmp_path / "other.mcap"
    assert find_recording(incident, given, here) == given
    assert find_recording(Incident(id=2, stamp=NOW, kind=IncidentKind.ESTOP), None, here) is None


def test_json_always_has_the_fields_scripts_rely_on() -> None:
    data = incident_json(Incident(id=3, stamp=NOW, kind=IncidentKind.NEAR_MISS, reason="person at 0.1 m"))
    assert {"id", "time", "kind", "x", "y", "reason"} <= set(data)
    assert data["x"] is None and data["y"] is None and data["kind"] == "near_miss"
