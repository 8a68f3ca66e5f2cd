"""Safety's incident store on the real stack: an e-stop is remembered with where the robot was and the
recording it is in, survives a restart of safety and warns the dry run of a later plan going there
(`tether incidents` lists it and shows its timeline); only the operator's token forgets an incident
(and the forgetting is a safety event); a store another program holds locked, or a file that is not
a database, does not stop safety from checking plans, and `safety/incidents` names the fault (what
happened meanwhile is kept, and written once the file is free)."""

from __future__ import annotations

import json
import math
import sqlite3
import time
from collections.abc import Iterator

import pytest

from schemas import keys
from schemas.executor import ExecutePlanGoal, PlanStatus
from schemas.incidents import (
    ForgetIncident,
    Incident,
    IncidentKind,
    IncidentList,
    IncidentQuery,
    IncidentReport,
)
from schemas.safety import Decision, EstopSource
from services.safety.node import REPORT_REACH
from services.safety.operator import read_token
from tests.fastsim import FAST_SIM
from tests.integration.conftest import Stack, start_stack, stop_stack, tether_cli
from tests.procs import wait_until
from tests.watch import Watch
from tether.client import PlanSender, reset_estop, trigger_estop

PLAN_TIMEOUT = 120.0
# How long a live recording may take to hold the rows around an incident (s).
ROWS_TIMEOUT = 15.0


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    s = start_stack(tmp_path_factory.mktemp("incidents"), realtime_factor=10.0, sim_options=FAST_SIM)
    try:
        yield s
    finally:
        stop_stack(s)


def listed(stack: Stack, query: IncidentQuery | None = None) -> IncidentList:
    return stack.node.call(keys.INCIDENTS, query or IncidentQuery(), timeout=5.0)


def restart_safety(stack: Stack) -> None:
    stack.supervisor.stop("safety")
    stack.supervisor.start("safety")
    assert not stack.node.wait_alive(["safety"], 60.0), stack.supervisor.log_tail("safety")
    assert Watch(stack.node, keys.HEARTBEAT).latest(timeout=10.0) is not None, "no heartbeat after the restart"


def report(stack: Stack, reason: str, metres_away: float = 0.5) -> Incident:
    """A dropped object reported as the sim would, `metres_away` east of the robot; the incident
    safety records for it."""
    new = Watch(stack.node, keys.NEW_INCIDENT)
    here = Watch(stack.node, keys.ODOM).latest(timeout=5.0)
    assert here is not None, "no odometry"
    x, y = round(here.pose.x + metres_away, 3), round(here.pose.y, 3)
    # A kind only safety may record is ignored; published first, it would arrive first.
    stack.node.publish(keys.INCIDENT_REPORT, IncidentReport(kind=IncidentKind.ESTOP, reason=f"pretend {reason}"))
    stack.node.publish(
        keys.INCIDENT_REPORT,
        IncidentReport(kind=IncidentKind.DROPPED, reason=reason, objects=["red cup"], x=x, y=y),
    )
    incident = new.wait_for(lambda i: reason in i.reason, timeout=10.0)
    assert incident is not None, "the report was not recorded"
    assert all(i.kind is not IncidentKind.ESTOP for i in new.messages), "a reported e-stop was taken"
    assert (incident.kind, incident.objects) == (IncidentKind.DROPPED, ["red cup"])
    if metres_away <= REPORT_REACH:
        assert (incident.x, incident.y) == (x, y)
    return incident


def test_a_report_placed_far_from_the_robot_is_recorded_where_the_robot_was(stack: Stack) -> None:
    """A broken or hostile reporter could put caution zones anywhere: a drop 8 m from the robot is not where it says."""
    here = Watch(stack.node, keys.ODOM).latest(timeout=5.0)
    assert here is not None
    incident = report(stack, "dropped far away, it says", metres_away=REPORT_REACH + 5.0)
    assert incident.x is not None and incident.y is not None
    assert math.dist((incident.x, incident.y), (here.pose.x, here.pose.y)) < 0.5, incident
    assert f"over {REPORT_REACH:g} m from the robot: placed where it was" in incident.reason


def test_an_estop_is_remembered_where_the_robot_was_survives_a_restart_and_warns_a_later_plan(stack: Stack) -> None:
    odom = Watch(stack.node, keys.ODOM)
    new = Watch(stack.node, keys.NEW_INCIDENT)
    here = odom.latest(timeout=5.0)
    assert here is not None
    try:
        assert trigger_estop(stack.node, EstopSource.OPERATOR, "a child ran into the kitchen") is not None
        incident = new.wait_for(lambda i: i.kind is IncidentKind.ESTOP, timeout=10.0)
        assert incident is not None, "the e-stop was not recorded"
        assert incident.source == "operator" and "a child ran into the kitchen" in incident.reason
        assert incident.x is not None and incident.y is not None
        assert math.hypot(incident.x - here.pose.x, incident.y - here.pose.y) < 0.05
        assert incident.hand is not None  # the arm's joints were known
        assert incident.recording.endswith(".mcap"), incident.recording
        assert incident in listed(stack).incidents

        restart_safety(stack)
        after = listed(stack, IncidentQuery(kinds=[IncidentKind.ESTOP]))
        assert after.store == "" and incident in after.incidents
    finally:
        assert reset_estop(stack.node, str(stack.token_file)).ok

    # A later plan going there is told of it in its dry run.
    there = json.dumps({"plan": [{"action": "navigate_to", "x": incident.x + 0.3, "y": incident.y}]})
    checked = PlanSender(stack.node).run(ExecutePlanGoal(text=there, dry_run=True), PLAN_TIMEOUT).result
    assert checked is not None and checked.status is PlanStatus.SUCCEEDED, checked
    warned = [w for w in checked.warnings if "a child ran into the kitchen" in w]
    assert warned and warned[0].startswith("e-stop ") and " ago (operator: " in warned[0], checked.warnings

    # The operator's command line lists it and shows it with its timeline from the recording.
    shown = tether_cli(stack, "incidents", "--kind", "estop", "--json")
    assert shown.returncode == 0, shown.stderr
    rows = json.loads(shown.stdout)["incidents"]
    assert [r["id"] for r in rows] == [incident.id] and rows[0]["x"] == incident.x, rows
    # The recording is live: the chunk holding the e-stop is on disk within the recorder's flush
    # interval (1 s), later on a loaded machine; shown again until it is.
    deadline = time.monotonic() + ROWS_TIMEOUT
    while True:
        one = tether_cli(stack, "incidents", "show", str(incident.id), "--json")
        assert one.returncode == 0, one.stderr
        detail = json.loads(one.stdout)
        assert detail["incident"]["reason"] == incident.reason and detail["recording"] == incident.recording
        if any(r["kind"] == "estop" and abs(r["dt"]) < 2.0 for r in detail["rows"]):
            break
        assert time.monotonic() < deadline, detail["rows"]
    missing = tether_cli(stack, "incidents", "show", "999999", "--json")
    assert missing.returncode == 2 and "no incident 999999" in json.loads(missing.stdout)["error"]


def test_only_the_operators_token_forgets_an_incident_and_the_forgetting_is_an_event(stack: Stack) -> None:
    incident = report(stack, "the cup slipped out of the gripper")
    events = Watch(stack.node, keys.SAFETY_EVENTS)
    # What an agent could send: any name, no token (or a guessed one).
    refused = stack.node.call(
        keys.FORGET_INCIDENT,
        ForgetIncident(operator="agent", token="guess", id=incident.id, reason="it never happened"),
        timeout=5.0,
    )
    assert not refused.ok and "not the operator's token" in refused.message, refused
    assert incident in listed(stack).incidents
    token = read_token(stack.token_file)
    done = stack.node.call(
        keys.FORGET_INCIDENT,
        ForgetIncident(operator="alice", token=token, id=incident.id, reason="the gripper pads were replaced"),
        timeout=5.0,
    )
    assert done.ok and done.changed == [incident.id], done
    assert incident.id not in [i.id for i in listed(stack).incidents]
    forgotten = events.wait_for(lambda e: e.decision is Decision.FORGOTTEN, timeout=5.0)
    assert forgotten is not None and f"incident {incident.id} forgotten by operator alice" in forgotten.reason
    assert token not in repr(events.messages)
    again = stack.node.call(
        keys.FORGET_INCIDENT, ForgetIncident(operator="alice", token=token, id=incident.id, reason="x"), timeout=5.0
    )
    assert not again.ok and "already forgotten" in again.message


def test_a_locked_store_does_not_stop_safety_from_checking_and_is_written_once_free(stack: Stack) -> None:
    path = stack.tmp / f"incidents-{stack.settings.robot}.sqlite"
    holder = sqlite3.connect(path, timeout=0.0)
    try:
        holder.execute("BEGIN EXCLUSIVE")  # another program holds the file
        kept = report(stack, "dropped while another program held the store")
        assert wait_until(lambda: "locked" in listed(stack).store, 10.0), listed(stack).store
        assert kept in listed(stack).incidents  # kept in memory, listed with the fault
        stairs = json.dumps({"plan": [{"action": "navigate_to", "target": "stairs"}]})
        refused = PlanSender(stack.node).run(ExecutePlanGoal(text=stairs, dry_run=True), PLAN_TIMEOUT).result
        assert refused is not None and (refused.status, refused.stage) == (PlanStatus.REJECTED, "safety"), refused
        kitchen = json.dumps({"plan": [{"action": "navigate_to", "target": "kitchen"}]})
        approved = PlanSender(stack.node).run(ExecutePlanGoal(text=kitchen, dry_run=True), PLAN_TIMEOUT).result
        assert approved is not None and approved.status is PlanStatus.SUCCEEDED, approved
    finally:
        holder.rollback()
        holder.close()
    # Once free, safety writes what it kept (it retries a faulted file every few seconds).
    assert wait_until(lambda: listed(stack).store == "", 30.0), listed(stack).store
    rows = sqlite3.connect(path).execute("SELECT reason FROM incidents").fetchall()
    assert (kept.reason,) in rows


def test_a_store_file_that_is_not_a_database_does_not_stop_safety_from_checking(stack: Stack) -> None:
    path = stack.tmp / f"incidents-{stack.settings.robot}.sqlite"
    assert path.exists()
    stack.supervisor.stop("safety")
    path.write_bytes(b"not a database " * 1000)
    stack.supervisor.start("safety")
    assert not stack.node.wait_alive(["safety"], 60.0), stack.supervisor.log_tail("safety")
    assert Watch(stack.node, keys.HEARTBEAT).latest(timeout=10.0) is not None

    faulty = listed(stack)
    assert str(path) in faulty.store and "not a database" in faulty.store, faulty.store
    # Safety checks as before: a plan into the stairs is refused, one to the kitchen is approved.
    stairs = json.dumps({"plan": [{"action": "navigate_to", "target": "stairs"}]})
    refused = PlanSender(stack.node).run(ExecutePlanGoal(text=stairs, dry_run=True), PLAN_TIMEOUT).result
    assert refused is not None and (refused.status, refused.stage) == (PlanStatus.REJECTED, "safety"), refused
    assert "stairs" in refused.reason
    kitchen = json.dumps({"plan": [{"action": "navigate_to", "target": "kitchen"}]})
    approved = PlanSender(stack.node).run(ExecutePlanGoal(text=kitchen, dry_run=True), PLAN_TIMEOUT).result
    assert approved is not None and approved.status is PlanStatus.SUCCEEDED, approved
    # What happens meanwhile is kept in memory, listed with the fault.
    kept = report(stack, "dropped while the store was broken")
    now = listed(stack)
    assert kept in now.incidents and now.store == faulty.store
