"""Safety's incident reports against a reporter that loops: each reporter's kinds have a budget of their
own (the executor's grasp_failed, the robot's dropped and collision), each with the documented limits.
With safety on a Recorder and the watch's clock held still, so no budget refills while a test runs."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from schemas import keys
from schemas.incidents import Incident, IncidentKind, IncidentReport
from services.safety.incidents import REPORT_BURST, IncidentStore
from tests.unit.test_safety_node import FakeClock, Recorder, Start
from tests.unit.test_safety_node import start as start  # the fixture, shared


def published(node: Recorder, kind: IncidentKind) -> list[Incident]:
    with node.changed:
        return [m for path, m in node.sent if path == keys.NEW_INCIDENT.path and m.kind is kind]


def report(node: Recorder, kind: IncidentKind, n: int) -> None:
    on_report: Any = node.callbacks[keys.INCIDENT_REPORT.path]
    for i in range(n):
        on_report(IncidentReport(kind=kind, reason=f"{kind} {i}"))


def test_an_executor_flooding_grasp_failed_leaves_the_robots_reports_their_budget(start: Start, tmp_path: Path) -> None:
    """One budget for all reports: an executor reporting grasp_failed in a loop used it up, and the
    robot's collision after it was dropped (never recorded). The executor's flood is still cut at the
    documented burst."""
    store = IncidentStore(tmp_path / "incidents.sqlite")
    node, safety = start(incidents=store)
    safety.watch.clock = FakeClock(100.0)
    report(node, IncidentKind.GRASP_FAILED, 3 * REPORT_BURST)
    report(node, IncidentKind.COLLISION, 1)

    node.wait_for(
        lambda sent: any(path == keys.NEW_INCIDENT.path and m.kind is IncidentKind.COLLISION for path, m in sent)
    )
    # Recorded in the order noted: every grasp_failed taken was published before the collision.
    assert len(published(node, IncidentKind.GRASP_FAILED)) == REPORT_BURST
    safety.close()
    store.close()


def test_the_robots_kinds_share_one_budget_with_the_documented_burst(start: Start, tmp_path: Path) -> None:
    """The robot's dropped and collision reports draw on one budget: a burst of REPORT_BURST, no more,
    and the executor's grasp_failed is still taken after it."""
    store = IncidentStore(tmp_path / "incidents.sqlite")
    node, safety = start(incidents=store)
    safety.watch.clock = FakeClock(100.0)
    report(node, IncidentKind.DROPPED, REPORT_BURST // 2)
    report(node, IncidentKind.COLLISION, 2 * REPORT_BURST)
    report(node, IncidentKind.GRASP_FAILED, 1)

    node.wait_for(
        lambda sent: any(path == keys.NEW_INCIDENT.path and m.kind is IncidentKind.GRASP_FAILED for path, m in sent)
    )
    dropped, collisions = published(node, IncidentKind.DROPPED), published(node, IncidentKind.COLLISION)
    assert len(dropped) == REPORT_BURST // 2
    assert len(dropped) + len(collisions) == REPORT_BURST
    safety.close()
    store.close()
