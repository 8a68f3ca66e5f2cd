"""`tether inspect`: the timeline rows and the map, from small recordings written with the real writer."""

from __future__ import annotations

import json
import struct
import time
from pathlib import Path
from typing import Any

import msgspec
import pytest
import typer
from hypothesis import given, settings
from hypothesis import strategies as st
from matplotlib import image
from typer.testing import CliRunner

from schemas import keys
from schemas.actions import Feedback, GoalResponse, GoalState, ResultResponse, SendGoal
from schemas.common import ErrorKind, Pose2D, ServiceError, Stage
from schemas.executor import (
    ExecutePlanFeedback,
    ExecutePlanGoal,
    ExecutePlanResult,
    PlanStatus,
    StepResult,
    StepStatus,
)
from schemas.plan import GroundedPlan, NavigateStep, Plan, PlanApproved, PlanText, Step
from schemas.robot import NavigateToPoseGoal, NavigateToPoseResult, Odometry, Twist
from schemas.safety import ALREADY_LATCHED, Decision, EStop, EstopSource, EstopState, Rule, SafetyEvent, SafetyStatus
from schemas.trace import TraceRecord
from schemas.world import PerceivedHuman, PerceivedHumans
from services.recorder.mapview import draw_map, estop_points, track_of, vetoed_goals
from services.recorder.mcapfile import Provenance, Recording, SourceFile
from services.recorder.reader import read_recording
from services.recorder.recorded import recorded_world
from services.recorder.timeline import (
    SAME_CHANGE,
    EventKind,
    Level,
    RobotState,
    Row,
    Timeline,
    build_timeline,
    told_by_safety,
)
from services.runtime import encode
from services.worldmodel import world_path
from tether.inspect import inspect

ROBOT = "r1"
T0 = 1_800_000_000_000_000_000  # ns
PLAN_ID = "plan0001aaaa"
NAV_ID = "nav0001bbbb"
VETO_ID = "veto0001cccc"
PLAN_TEXT = '{"plan": [{"action": "navigate_to", "target": "coffee table"}]}'
COFFEE_TABLE = Pose2D(x=8.0, y=1.75, yaw=1.5708)
STAIRS = Pose2D(x=11.2, y=8.0, yaw=1.5708)
POLICY = Path(__file__).parents[2] / "services" / "safety" / "policy.toml"


class Writer:
    """A recording written message by message at chosen times (seconds after T0). With `beating`,
    safety's heartbeat goes out every BEAT seconds in between, as the last beat() left it."""

    BEAT = 0.1

    def __init__(self, path: Path, provenance: Provenance | None = None, beating: bool = False) -> None:
        self.path = path
        self.recording = Recording(path, ROBOT, provenance=provenance)
        self.beating = beating
        self.last_beat: tuple[float, SafetyStatus] | None = None

    def put(self, t: float, key: str, message: Any) -> None:
        while self.beating and self.last_beat is not None and self.last_beat[0] + self.BEAT < t:
            at, status = self.last_beat
            self.last_beat = (at + self.BEAT, status)
            self._record(at + self.BEAT, keys.HEARTBEAT.key(ROBOT), encode(status))
        self._record(t, key, message if isinstance(message, bytes) else encode(message))

    def _record(self, t: float, key: str, payload: bytes) -> None:
        assert self.recording.record(key, payload, log_time=T0 + int(t * 1e9))

    def topic(self, t: float, topic: keys.Topic[Any], message: Any) -> None:
        self.put(t, topic.key(ROBOT), message)

    def trace(self, t: float, service: str, path: str, query: Any, reply: Any = None, error: str = "") -> None:
        record = TraceRecord(
            stamp=1.8e9 + t,
            service=service,
            key=path,
            duration=0.001,
            query=msgspec.Raw(encode(query)),
            reply=msgspec.Raw(encode(reply) if reply is not None else b"null"),
            error=error,
        )
        self.put(t, keys.trace_key(ROBOT, service, path), record)

    def event(self, t: float, key: str, decision: Decision, reason: str = "", **extra: Any) -> None:
        command = extra.pop("command", None)
        raw = msgspec.Raw(encode(command) if command is not None else b"null")
        event = SafetyEvent(stamp=1.8e9 + t, key=key, decision=decision, reason=reason, command=raw, **extra)
        self.topic(t, keys.SAFETY_EVENTS, event)

    def odom(self, t: float, x: float, y: float, yaw: float = 0.0, speed: float = 0.0) -> None:
        pose = Pose2D(x=x, y=y, yaw=yaw)
        self.topic(t, keys.ODOM, Odometry(stamp=1.8e9 + t, sim_time=t, pose=pose, linear_x=speed, angular_z=0.0))

    def beat(self, t: float, latched: bool = False, scale: float = 1.0, seq: int = 0, reason: str = "") -> None:
        estop = EstopState(latched=latched, source="operator" if latched else "", reason="stop!" if latched else "")
        status = SafetyStatus(seq=seq, stamp=1.8e9 + t, estop=estop, speed_scale=scale, speed_reason=reason)
        self.topic(t, keys.HEARTBEAT, status)
        self.last_beat = (t, status)

    def feedback(self, t: float, step: int, status: StepStatus, message: str) -> None:
        fb = ExecutePlanFeedback(
            stage=Stage.EXECUTE, step=step, action="navigate_to", status=status, message=message, label=str(step + 1)
        )
        self.topic(t, keys.EXECUTE_PLAN.feedback, Feedback(goal_id=PLAN_ID, feedback=fb))

    def finish(self) -> Path:
        self.recording.finish()
        return self.path


def household() -> Provenance:
    return Provenance(ROBOT, world=SourceFile.read(world_path("household")), policy=SourceFile.read(POLICY))


def write_incident(path: Path) -> Path:
    """A plan that drives to the coffee table, a goal vetoed for the stairs, an e-stop and its reset."""
    w = Writer(path, household(), beating=True)
    w.beat(0.0, seq=1)
    w.odom(0.01, 6.0, 1.2)
    w.topic(0.02, keys.HUMANS, PerceivedHumans(stamp=0.0, humans=[human(9.5, 1.5)]))
    plan = Plan(steps=[Step(action="navigate_to", target="coffee table")], description="to the coffee table")  # type: ignore[arg-type]
    grounded = GroundedPlan(steps=[NavigateStep(target="coffee table", goal=COFFEE_TABLE)], source=plan, labels=["1"])
    w.trace(1.0, "parser", keys.PLAN_PARSE.path, PlanText(text=PLAN_TEXT), plan)
    w.trace(1.01, "resolver", keys.PLAN_RESOLVE.path, plan, grounded)
    w.event(1.02, keys.PLAN_CHECK.path, Decision.APPROVED, "step 1: coffee table is on the map", command=grounded)
    w.trace(1.03, "safety", keys.PLAN_CHECK.path, grounded, PlanApproved(checks=["step 1: fine"]))
    submitted = SendGoal(goal_id=PLAN_ID, goal=ExecutePlanGoal(text=PLAN_TEXT))
    w.trace(1.04, "executor", keys.EXECUTE_PLAN.send_goal.path, submitted, GoalResponse(goal_id=PLAN_ID, accepted=True))
    w.feedback(1.05, 0, StepStatus.RUNNING, "moving the base: coffee table -> (8.00, 1.75, 90°)")
    drive = NavigateToPoseGoal(pose=COFFEE_TABLE, path=[Pose2D(x=7.0, y=1.2)], max_speed=0.6)
    nav = SendGoal(goal_id=NAV_ID, goal=drive)
    w.event(1.1, keys.CMD_NAVIGATE.send_goal.path, Decision.APPROVED, command=nav, checks=[Rule.KEEP_OUT])
    w.trace(1.11, "safety", keys.CMD_NAVIGATE.send_goal.path, nav, GoalResponse(goal_id=NAV_ID, accepted=True))
    for i in range(1, 40):  # the high-rate streams while it drives
        t = 1.1 + i * 0.05
        w.odom(t, 6.0 + i * 0.05, 1.2 + i * 0.0125, speed=0.5)
        w.feedback(t, 0, StepStatus.RUNNING, "moving the base: coffee table -> (8.00, 1.75, 90°)")
    w.odom(3.2, 8.0, 1.75, yaw=1.5708)
    done = ResultResponse[NavigateToPoseResult](
        goal_id=NAV_ID, state=GoalState.SUCCEEDED, result=NavigateToPoseResult(pose=COFFEE_TABLE, message="reached")
    )
    w.trace(3.3, "safety", keys.CMD_NAVIGATE.get_result.path, {"goal_id": NAV_ID}, done)
    w.feedback(3.31, 0, StepStatus.SUCCEEDED, "reached coffee table")
    result = ExecutePlanResult(
        status=PlanStatus.SUCCEEDED,
        stage=Stage.EXECUTE,
        steps=[StepResult(index=0, action="navigate_to", status=StepStatus.SUCCEEDED, label="1")],
    )
    w.topic(3.32, keys.EXECUTE_PLAN.status, {"goal_id": PLAN_ID, "state": "succeeded", "message": "", "stamp": 0.0})
    reply = ResultResponse[ExecutePlanResult](goal_id=PLAN_ID, state=GoalState.SUCCEEDED, result=result)
    w.trace(3.33, "executor", keys.EXECUTE_PLAN.get_result.path, {"goal_id": PLAN_ID}, reply)
    # A goal into the stairs, vetoed; the trace of its refusal adds nothing.
    veto = SendGoal(goal_id=VETO_ID, goal=NavigateToPoseGoal(pose=STAIRS))
    why = "at the goal (11.20, 8.00) the base's footprint would be in keep-out zone 'stairs'"
    w.event(4.0, keys.CMD_NAVIGATE.send_goal.path, Decision.VETOED, why, rule=Rule.KEEP_OUT, command=veto)
    refused = GoalResponse(goal_id=VETO_ID, accepted=False, reason=f"vetoed by safety: {why}", kind=ErrorKind.VETOED)
    w.trace(4.01, "safety", keys.CMD_NAVIGATE.send_goal.path, veto, refused)
    # A person comes near: the heartbeat and safety's event both say so; one row.
    near = "operator is 1.2 m away"
    w.event(5.0, keys.HEARTBEAT.path, Decision.LIMITED, near, rule=Rule.HUMAN_SEPARATION, values={"scale": 0.4})
    w.beat(5.02, scale=0.4, seq=100, reason=near)
    w.topic(5.03, keys.HUMANS, PerceivedHumans(stamp=0.0, humans=[human(8.8, 2.9)]))
    # The e-stop: asked for, latched (heartbeat first, then the event), reset.
    w.topic(6.0, keys.ESTOP, EStop(source=EstopSource.OPERATOR, reason="stop!"))
    w.beat(6.001, latched=True, scale=0.4, seq=101)
    w.event(6.002, keys.ESTOP.path, Decision.LATCHED, "by operator: stop!", rule=Rule.ESTOP)
    w.beat(7.0, latched=True, scale=0.4, seq=102)
    w.event(8.0, keys.RESET.path, Decision.RESET, "by operator alice", checks=[Rule.OPERATOR])
    w.beat(8.01, latched=False, scale=0.4, seq=103)
    return w.finish()


def human(x: float, y: float) -> PerceivedHuman:
    return PerceivedHuman(id="operator", name="operator", pose=Pose2D(x=x, y=y))


def timeline_of(path: Path, everything: bool = False) -> Timeline:
    return build_timeline(read_recording(path), everything)


def summaries(rows: list[Row]) -> list[str]:
    return [f"{row.kind}: {row.text}" for row in rows]


@pytest.fixture
def incident(tmp_path: Path) -> Path:
    return write_incident(tmp_path / "incident.mcap")


def test_the_incident_reads_as_one_row_per_thing_that_happened(incident: Path) -> None:
    rows = timeline_of(incident).rows
    assert [(row.kind, row.key) for row in rows] == [
        (EventKind.PLAN, "plan/parse"),
        (EventKind.PLAN, "plan/resolve"),
        (EventKind.DECISION, "safety/check_plan"),
        (EventKind.PLAN, "plan/execute"),
        (EventKind.STEP, "plan/execute"),
        (EventKind.COMMAND, "cmd/navigate_to_pose/_action/send_goal"),
        (EventKind.COMMAND, "cmd/navigate_to_pose"),
        (EventKind.STEP, "plan/execute"),
        (EventKind.PLAN, "plan/execute"),
        (EventKind.DECISION, "cmd/navigate_to_pose/_action/send_goal"),
        (EventKind.SPEED, "safety/heartbeat"),
        (EventKind.ESTOP, "safety/estop"),
        (EventKind.ESTOP, "safety/estop"),
        (EventKind.RESET, "safety/reset"),
    ], "\n".join(summaries(rows))
    text = summaries(rows)
    assert text[0] == "plan: parsed 'to the coffee table': 1 steps (json): navigate_to coffee table"
    assert text[1] == "plan: resolved 1 steps: navigate_to coffee table (8.00, 1.75, 90°)"
    assert text[2] == "decision: plan approved by safety: step 1: coffee table is on the map"
    assert text[3] == f"plan: plan plan0001 submitted: {PLAN_TEXT!r}: accepted"
    assert text[4] == "step: step 1 navigate_to: running: moving the base: coffee table -> (8.00, 1.75, 90°)"
    assert text[5] == "command: navigate_to_pose goal (8.00, 1.75, 90°) via 1 waypoint at ≤0.60 m/s: approved"
    assert text[6] == (
        "command: navigate_to_pose goal (8.00, 1.75, 90°) via 1 waypoint at ≤0.60 m/s: succeeded: reached; "
        "ended at (8.00, 1.75, 90°)"
    )
    assert text[7] == "step: step 1 navigate_to: succeeded: reached coffee table"
    assert text[8] == "plan: plan plan0001 succeeded at stage execute; steps: 1 succeeded"
    assert text[10] == "speed: speed scale 0.4: operator is 1.2 m away"
    assert text[11] == "estop: e-stop requested by operator: stop!"
    assert text[12] == "estop: e-stop latched by operator: stop!"
    assert text[13] == "reset: e-stop reset by operator alice"


def test_an_estop_asked_for_while_latched_reads_as_asked_again_not_as_a_second_latch(tmp_path: Path) -> None:
    w = Writer(tmp_path / "again.mcap")
    w.beat(0.0, latched=True, seq=1)
    w.event(0.5, keys.ESTOP.path, Decision.LATCHED, "by operator: stop!", rule=Rule.ESTOP)
    again = "by agent: looping; already latched by operator: stop!"
    w.event(1.0, keys.ESTOP.path, Decision.LATCHED, again, rule=Rule.ESTOP, values={ALREADY_LATCHED: 1.0})
    rows = [row for row in timeline_of(w.finish()).rows if row.key == keys.ESTOP.path]
    assert summaries(rows)[-2:] == [
        "estop: e-stop latched by operator: stop!",
        f"estop: e-stop asked for again while latched: {again}",
    ]
    assert rows[-1].level is Level.WARN


def test_a_veto_names_the_rule_the_target_and_the_reason(incident: Path) -> None:
    veto = next(row for row in timeline_of(incident).rows if row.decision is Decision.VETOED)
    assert veto.text == (
        "vetoed cmd/navigate_to_pose (keep_out): goal (11.20, 8.00, 90°): at the goal (11.20, 8.00) the base's "
        "footprint would be in keep-out zone 'stairs'"
    )
    assert (veto.kind, veto.level, veto.rule, veto.target) == (EventKind.DECISION, Level.BAD, "keep_out", (11.2, 8.0))


def test_each_row_carries_the_robot_state_of_its_moment(incident: Path) -> None:
    rows = timeline_of(incident).rows
    by_text = {row.text: row.state for row in rows}
    approved = by_text["navigate_to_pose goal (8.00, 1.75, 90°) via 1 waypoint at ≤0.60 m/s: approved"]
    assert (approved.x, approved.y, approved.speed, approved.estop, approved.speed_scale) == (6.0, 1.2, 0.0, False, 1.0)
    arrived = next(row.state for row in rows if row.kind is EventKind.STEP and "succeeded" in row.text)
    assert (arrived.x, arrived.y, arrived.yaw) == (8.0, 1.75, 1.5708)
    requested, latched = (row.state for row in rows if row.kind is EventKind.ESTOP)
    assert (requested.estop, latched.estop, latched.speed_scale) == (False, True, 0.4)
    assert rows[-1].state.estop is False
    assert rows[0].t == pytest.approx(1.0) and rows[-1].t == pytest.approx(8.0)


def test_high_rate_streams_only_set_the_state_unless_everything_is_asked_for(incident: Path) -> None:
    recording = read_recording(incident)
    quiet = build_timeline(recording).rows
    assert not {row.source for row in quiet} & {keys.ODOM.path, keys.HUMANS.path}
    assert sum(row.kind is EventKind.STEP for row in quiet) == 2  # 40 identical feedbacks are one row
    every = build_timeline(recording, everything=True).rows
    assert sum(row.source == keys.ODOM.path for row in every) == 41
    assert sum(row.source == keys.HEARTBEAT.path for row in every) >= 40
    assert len(every) > len(quiet) + 120


def test_a_change_seen_only_in_the_heartbeat_is_a_row(tmp_path: Path) -> None:
    w = Writer(tmp_path / "beats.mcap")
    w.beat(0.0, latched=True)  # latched from before the recording
    w.beat(0.1, latched=False)  # cleared: no reset event in the file
    w.beat(0.2, scale=0.0, reason="operator is 0.3 m away: paused")
    w.beat(0.3, latched=True, scale=0.0)
    w.odom(1.0, 1.0, 1.0)
    w.beat(1.5, latched=True, scale=0.0)  # 1.2 s without a heartbeat while other traffic came
    w.beat(3.0, latched=True, scale=0.0)  # 1.5 s without anything at all
    w.odom(4.6, 1.0, 1.0)  # and no heartbeat for the last 1.6 s
    rows = timeline_of(w.finish()).rows
    assert summaries(rows) == [
        "estop: e-stop latched when the recording starts: by operator: stop!",
        "reset: e-stop cleared (seen in the heartbeat)",
        "speed: speed scale 1 -> 0: operator is 0.3 m away: paused",
        "estop: e-stop latched (seen in the heartbeat): by operator: stop!",
        "heartbeat: no heartbeat from safety for 1.20 s before this one: the robot stops without one",
        "heartbeat: nothing at all was recorded for 1.50 s, heartbeats included (recorder or network stalled?)",
        "heartbeat: no heartbeat from safety in the last 1.60 s of the recording: the robot stops without one",
    ]
    assert [row.decision for row in rows[:4]] == [Decision.LATCHED, Decision.RESET, Decision.LIMITED, Decision.LATCHED]


def test_a_cmd_vel_stream_is_one_row_per_change(tmp_path: Path) -> None:
    w = Writer(tmp_path / "teleop.mcap")
    key = keys.TELEOP_CMD_VEL.path
    for i in range(10):
        w.event(i * 0.1, key, Decision.APPROVED, command=Twist(linear_x=0.3))
    for i in range(5):
        sent = Twist(linear_x=0.6)
        w.event(1 + i * 0.1, key, Decision.CLAMPED, "asked 0.9 m/s", rule=Rule.BASE_SPEED, command=sent)
    w.event(2.0, key, Decision.APPROVED, command=Twist())
    assert summaries(timeline_of(w.finish()).rows) == [
        "command: cmd/teleop/cmd_vel 0.30 m/s, 0.00 rad/s: approved (and 9 more like it)",
        "decision: clamped cmd/teleop/cmd_vel (base_speed): sent 0.60 m/s, 0.00 rad/s: asked 0.9 m/s "
        "(and 4 more like it)",
        "command: cmd/teleop/cmd_vel 0.00 m/s, 0.00 rad/s: approved",
    ]


def test_failures_and_bad_messages_are_rows_too(tmp_path: Path) -> None:
    w = Writer(tmp_path / "failures.mcap")
    parse_error = ServiceError(kind=ErrorKind.INVALID_REQUEST, message="no steps found", line=1, column=3)
    w.trace(0.1, "parser", keys.PLAN_PARSE.path, PlanText(text="dance"), parse_error)
    w.trace(0.2, "safety", keys.CMD_NAVIGATE.send_goal.path, {}, error="invalid request: missing goal_id")
    w.put(0.3, keys.ODOM.key(ROBOT), b'{"pose": "somewhere"}')
    w.put(0.4, keys.ODOM.key(ROBOT), b'{"pose": "elsewhere"}')
    w.put(0.5, keys.ESTOP.key(ROBOT), b'"stop"')
    rows = timeline_of(w.finish()).rows
    assert summaries(rows)[:2] == [
        "plan: parse failed: invalid_request: no steps found (line 1, column 3)",
        "command: navigate_to_pose goal refused: invalid request: missing goal_id",
    ]
    bad, estop = rows[2], rows[3]
    assert (bad.kind, bad.key, bad.repeats, bad.level) == (EventKind.BAD, "robot/odom", 1, Level.BAD)
    assert "does not decode" in bad.text and "Odometry" in bad.text
    assert estop.text == "an e-stop message that does not decode (6 bytes)"


def test_a_file_cut_short_is_read_as_far_as_it_is_whole(tmp_path: Path) -> None:
    w = Writer(tmp_path / "whole.mcap")
    w.beat(0.0)
    w.topic(0.1, keys.ESTOP, EStop(source=EstopSource.WATCHDOG, reason="no odometry"))
    w.recording.flush()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(w.path.read_bytes())  # as a killed recorder leaves it: no summary
    w.finish()
    recording = read_recording(cut)
    assert not recording.complete
    assert summaries(build_timeline(recording).rows) == ["estop: e-stop requested by watchdog: no odometry"]


def png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = struct.unpack(">II", data[16:24])
    return width, height


def test_the_map_is_a_png_of_the_world_with_the_path_vetoes_estops_and_people(incident: Path, tmp_path: Path) -> None:
    recording = read_recording(incident)
    timeline = build_timeline(recording)
    track = track_of(recording)
    assert track.path[0] == (6.0, 1.2) and track.path[-1] == (8.0, 1.75)
    assert track.people == {"operator": [(9.5, 1.5), (8.8, 2.9)]}
    vetoes, estops = vetoed_goals(timeline.rows), estop_points(timeline.rows)
    assert [(m.x, m.y, m.label) for m in vetoes] == [(11.2, 8.0, "keep_out @ 4.0 s")]
    assert [(m.x, m.y, m.label) for m in estops] == [(8.0, 1.75, "e-stop @ 6.0 s")]
    world = recorded_world(recording)
    output = tmp_path / "map.png"
    draw_map(output, "incident.mcap — robot r1", world, world.keep_out, track, vetoes, estops)
    width, height = png_size(output)
    assert 900 <= width <= 2000 and 400 <= height <= 1400 and width > height  # the flat is wider than deep
    pixels = image.imread(str(output))
    assert pixels.shape[:2] == (height, width)
    assert pixels.std() > 0.05  # something is drawn on it


def test_a_map_without_a_world_still_draws_the_path(tmp_path: Path) -> None:
    w = Writer(tmp_path / "bare.mcap")
    w.odom(0.0, 0.0, 0.0)
    w.odom(1.0, 2.0, 1.0)
    recording = read_recording(w.finish())
    output = tmp_path / "bare.png"
    draw_map(output, "bare", None, [], track_of(recording))
    width, height = png_size(output)
    assert width > 300 and height > 200


# The command


def flat(text: str) -> str:
    """Console output as one line (rich wraps it at the terminal's width)."""
    return " ".join(text.split())


@pytest.fixture
def cli() -> typer.Typer:
    app = typer.Typer()
    app.command()(inspect)
    return app


def test_inspect_prints_the_rows_as_json(cli: typer.Typer, incident: Path) -> None:
    result = CliRunner().invoke(cli, [str(incident), "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    messages = len(read_recording(incident).messages)
    assert (document["robot"], document["complete"], document["messages"]) == (ROBOT, True, messages)
    rows = document["rows"]
    assert len(rows) == 14
    veto = rows[9]
    assert [veto[k] for k in ("kind", "decision", "rule", "target")] == ["decision", "vetoed", "keep_out", [11.2, 8.0]]
    assert veto["state"] == {"x": 8.0, "y": 1.75, "yaw": 1.5708, "speed": 0.0, "estop": False, "speed_scale": 1.0}
    assert veto["source"] == "safety/events" and veto["t"] == pytest.approx(4.0)


def test_inspect_keys_selects_rows_by_key_expression(cli: typer.Typer, incident: Path) -> None:
    result = CliRunner().invoke(cli, [str(incident), "--json", "--keys", "cmd/**"])
    assert result.exit_code == 0, result.output
    assert [row["key"] for row in json.loads(result.stdout)["rows"]] == [
        "cmd/navigate_to_pose/_action/send_goal",
        "cmd/navigate_to_pose",
        "cmd/navigate_to_pose/_action/send_goal",
    ]
    bad = CliRunner().invoke(cli, [str(incident), "--keys", "a//b"])
    assert bad.exit_code == 2 and "not a valid key expression" in flat(bad.stderr)


def test_inspect_prints_a_table_and_draws_the_map(cli: typer.Typer, incident: Path, tmp_path: Path) -> None:
    output = tmp_path / "incident.png"
    result = CliRunner().invoke(cli, [str(incident), "--png", str(output)], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert "vetoed cmd/navigate_to_pose (keep_out)" in result.stdout
    assert "LATCHED" in result.stdout and "8.00, 1.75 90°" in result.stdout
    assert f"map written to {output}" in result.stderr
    assert png_size(output)[0] > 900


def test_inspect_notes_a_file_cut_short(cli: typer.Typer, incident: Path, tmp_path: Path) -> None:
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(incident.read_bytes()[: incident.stat().st_size // 2])
    result = CliRunner().invoke(cli, [str(cut)])
    assert result.exit_code == 0, result.output
    assert "was cut short: the file ends early" in flat(result.stderr)


@pytest.mark.parametrize(("content", "said"), [(None, "no such file"), (b"", "empty"), (b"hello", "not an MCAP")])
def test_inspect_refuses_a_missing_or_non_mcap_file(
    cli: typer.Typer, tmp_path: Path, content: bytes | None, said: str
) -> None:
    path = tmp_path / "x.mcap"
    if content is not None:
        path.write_bytes(content)
    result = CliRunner().invoke(cli, [str(path)])
    assert result.exit_code == 2
    assert said in flat(result.stderr)


def split_in_two(source: Path, directory: Path) -> tuple[Path, Path]:
    """The recording at `source` as the two parts a rotation would have written."""
    messages = read_recording(source).messages
    half = len(messages) // 2
    paths = []
    for n, chunk in enumerate((messages[:half], messages[half:])):
        path = directory / f"part{n}.mcap"
        began = chunk[0].log_time
        part = Recording(path, ROBOT, provenance=household(), part=n, run="run1", clock=lambda began=began: began)
        for message in chunk:
            part.record(message.key, message.data, log_time=message.log_time)
        part.finish()
        paths.append(path)
    return paths[0], paths[1]


def test_inspect_reads_the_parts_of_a_rotated_recording_as_one(
    cli: typer.Typer, incident: Path, tmp_path: Path
) -> None:
    first, second = split_in_two(incident, tmp_path)
    whole = CliRunner().invoke(cli, [str(incident), "--json"])
    joined = CliRunner().invoke(cli, [str(second), str(first), "--json"])  # in any order
    assert joined.exit_code == 0, joined.output
    document = json.loads(joined.stdout)
    assert document["parts"] == [str(first), str(second)]
    assert document["rows"] == json.loads(whole.stdout)["rows"]
    twice = CliRunner().invoke(cli, [str(first), str(first)])
    assert twice.exit_code == 2 and "given twice" in flat(twice.stderr)


def test_faults_incidents_and_recoveries_are_rows(tmp_path: Path) -> None:
    from schemas.incidents import Incident, IncidentKind
    from schemas.planner import Recovery, RecoveryOutcome
    from schemas.world import FaultInjected, FaultKind, InjectFault

    w = Writer(tmp_path / "recovered.mcap")
    slip = InjectFault(kind=FaultKind.SLIP, target="red_cup")
    w.trace(0.1, "sim", keys.SIM_FAULT.path, slip, FaultInjected(kind=FaultKind.SLIP, message="red cup slips next"))
    w.trace(0.2, "sim", keys.SIM_FAULT.path, InjectFault(kind=FaultKind.HIDE, target="ghost"), error="no ghost")
    dropped = Incident(id=4, stamp=1.8e9, kind=IncidentKind.DROPPED, reason="red cup fell", x=2.5, y=0.63)
    w.topic(0.3, keys.NEW_INCIDENT, dropped)
    recovery = Recovery(
        request_id="r1",
        number=1,
        stamp=1.8e9,
        outcome=RecoveryOutcome.SUCCEEDED,
        failed_goal="a" * 32,
        failure="precondition",
        step=3,
        goal_id="b" * 32,
    )
    w.topic(0.4, keys.PLANNER_RECOVERIES, recovery)
    rows = timeline_of(w.finish()).rows
    assert [(r.kind, r.level) for r in rows] == [
        (EventKind.WORLD, Level.WARN),
        (EventKind.WORLD, Level.WARN),
        (EventKind.INCIDENT, Level.WARN),
        (EventKind.RECOVERY, Level.GOOD),
    ]
    assert "fault slip red_cup injected in the simulation: red cup slips next" in rows[0].text
    assert "refused: no ghost" in rows[1].text
    assert rows[2].text == "incident 4 remembered: dropped at (2.50, 0.63): red cup fell"
    assert rows[2].target == (2.5, 0.63)
    assert rows[3].text.startswith("recovery 1 after precondition at step 3: succeeded as plan ")


def _row(log_time: int, decision: Decision | None, source: str) -> Row:
    return Row(0.0, log_time, EventKind.DECISION, "cmd/cmd_vel", "", RobotState(), source, decision=decision)


def _told_one_by_one(implied: Row, rows: list[Row]) -> bool:
    """What an implied row's check means, read row by row."""
    return any(
        r.decision is implied.decision and abs(r.log_time - implied.log_time) <= SAME_CHANGE * 1e9
        for r in rows
        if r.source == keys.SAFETY_EVENTS.path
    )


@settings(max_examples=300, deadline=None, derandomize=True, database=None)
@given(
    st.lists(
        st.tuples(
            st.integers(0, 5 * 10**9),
            st.sampled_from([Decision.VETOED, Decision.LATCHED, Decision.RESET, None]),
            st.sampled_from([keys.SAFETY_EVENTS.path, keys.HEARTBEAT.path]),
        ),
        max_size=30,
    ),
    st.integers(0, 5 * 10**9),
    st.sampled_from([Decision.VETOED, Decision.LATCHED, Decision.RESET, None]),
)
def test_an_implied_row_is_told_by_safety_exactly_when_an_event_is_near_it(
    events: list[tuple[int, Decision | None, str]], at: int, decision: Decision | None
) -> None:
    rows = [_row(t, d, source) for t, d, source in events]
    implied = _row(at, decision, keys.HEARTBEAT.path)
    assert told_by_safety(rows)(implied) == _told_one_by_one(implied, rows)


def test_many_implied_rows_are_checked_against_many_events_in_n_log_n() -> None:
    """16,000 of each took 11 s when every implied row read every event."""
    rows = [_row(k * 10**8, Decision.LATCHED, keys.SAFETY_EVENTS.path) for k in range(20_000)]
    implied = [_row(k * 10**8 + 5 * 10**7, Decision.RESET, keys.HEARTBEAT.path) for k in range(20_000)]
    started = time.thread_time()
    told = told_by_safety(rows)
    assert not any(told(r) for r in implied)
    assert time.thread_time() - started < 1.0
