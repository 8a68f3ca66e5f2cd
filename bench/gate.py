"""Action goals through the safety gate: send_goal from a client, through safety's checks, to the sim and back.

    python -m bench.gate --json                one JSON object on stdout, progress on stderr
    python -m bench.gate                       a short table
    python -m bench.gate --viewer --json       the same, then again with a hostile Foxglove viewer connected

Measured: the round trip of a `cmd/<action>/_action/send_goal` query from this process (standing in
for the executor) to safety, which checks the goal, forwards it on
`robot/<action>/_action/send_goal` to the sim, and relays the sim's accept reply back. The sim and
safety are real processes started by the Supervisor on their own robot name and ports (see
`bench.service`); the sim runs at real time (`--realtime-factor`: faster brings results sooner, but
pybullet then holds the sim's CPU and GIL). The goals are real and accepted, cycling through three
kinds that leave the robot where it is: `gripper` (open to 0.08 m, as it already is), `trajectory`
(all seven arm joints to where joint_states says they are, in 0.3 s) and `navigate` (to the pose
odometry reports). After each send_goal its result is fetched (get_result through safety, not
timed), so goals never pile up. Safety allows each action 10 goals a second (its default policy, a
token bucket), so goals of one kind are sent at most `--goals-per-second` (default 8).

Baseline: safety's bare relay (TETHER_BENCH_RELAY=sim): a raw Zenoh get to safety, which forwards
the bytes with a plain get to the sim's bare echo and replies with the first reply's bytes. The same
two processes and two hops, carrying the same request bytes, with no decoding and no checks. Each
goal is interleaved with one relay round trip, alternating which goes first.

Safety answers the goal on a kept worker thread (services/querypool.py; it waits for the sim's
reply, so never on Zenoh's callback thread), where the relay answers on the callback thread itself:
one hand-over the relay does not have. The sim answers on Zenoh's callback thread, as its echo
does, since no goal runs for it to preempt (each goal's result is fetched before the next), and
starts the accepted goal's thread after its reply. Both trace the goal after replying; safety's
decision is published on safety/events before the goal is forwarded. The camera (`--objects-hz`, 5 frames a second by
default) renders in a process of the sim's own (services/sim/README.md, The camera's process); it
used to hold the sim's GIL ~20 ms a frame, most of both tails. `--objects-hz 0.2` shows the path
without it.

With `--incidents N` safety starts with a memory of N incidents (services/safety/incidents.py),
spread at random over the flat's rooms, so caution zones and the plan check's warnings have a lot
to go through; the goals and the plan checks (`plan_check_*`: a `safety/check_plan` query of a
one-step plan to where the robot stands, which safety answers itself, interleaved with safety's
bare echo of the same bytes, `plan_check_echo_p50_ms`: one hop, as the check is) are then measured
against that store. Compare with a run without it for what the memory costs.

What the ratio is made of (measured 2026-11-29 on the 2-core VM, hop by hop with monotonic stamps in
each process, then in-process): the four Zenoh legs cost the gate what they cost the relay; the rest
is Python, in safety (the worker's hand-over, decoding, the check, the decision's event, signing and
sending the forward, encoding the reply) and in the sim (the MAC, decoding, its own keep-out check of
a navigation, the reply). At the bench's pace each process sleeps some 40 ms between goals, and on
this VM code run after such a sleep takes many times its warm time: the gate's checks take 4, 30 and
48 us (gripper, trajectory, navigate) called back to back, but 17, 118 and 278 us each after 40 ms
asleep (thread CPU time, so not waiting for the GIL), and the sim's keep-out check 13 us against 200
to 320. Churning 32 MB of memory between calls without sleeping leaves it warm (16 us); a 2000-step
loop is as quick after a sleep as before. The relay does almost no Python, so it pays little of this.

Hop by hop again (2026-11-29, one run of 150 goals a kind, gate p50 1.22 ms against the relay's
0.51; monotonic stamps in the client, safety and the sim, one clock for all three; medians in us for
gripper / trajectory / navigate): the client to safety's worker pool 131 / 128 / 198; the hand-over
to the worker 40 / 44 / 50; the motion lock and noting the goal 13 / 11 / 16; the decision 38 / 267
/ 413 (of it policy.check_trajectory 202, policy.check_navigation 284 and the hand's reach 79 for a
navigation; the e-stop, mode and rate checks some 20); the decision's event 22 / 24 / 29; encoding,
signing and the leg to the sim 165 / 177 / 244; the sim's MAC check 44 / 40 / 64, its decoding and
accept 42 / 60 / 208 (its keep-out check of a navigation 137); from the end of the sim's handler to
the reply in safety's hands 178 / 185 / 230 (58 / 60 / 71 of it the sim's sending); safety's reply
to the client 191 / 185 / 218. Total 906 / 1191 / 1748. The decision's wall time is its thread CPU
time: it waits for no lock or GIL. The median of all goals falls among the trajectories, so only
what every goal or a trajectory pays moves `ratio_p50`; the checks themselves
(services/safety/policy.py) are most of what is left. In one process, after 40 ms asleep against
back to back: policy.check_trajectory 368 us against 39, check_navigation 471 against 60, the reach
158 against 9, encoding a trajectory goal 25 against 1, signing one 80 to 121 against 2.6. A robot
action server asked `accept` again after preempting even when there was nothing to preempt, so the
sim checked every goal twice; it asks again only after a wait now (services/actionlib.py):
`ratio_p50` 2.43 before, 2.34 after (medians of four interleaved runs each, lower in each pair; gate
p50 1.31 and 1.29 ms, relay 0.53 and 0.55, p99 3.04 and 2.98). Signing now copies an HMAC keyed once
(58 to 91 us asleep; services/robotlink.py); end to end that is within the noise of three runs each
(gate p50 1.11 ms before and after). Relaying the goals' status topics, which the sim publishes as
its reply goes, costs the goals nothing measurable (two runs each: ratio 2.42 and 2.46 with it, 2.42
and 2.41 without). The trajectory check in plain floats, a point tested against a zone's bounding box
before shapely, and the grasp frame placed alone (2026-11-29): check_trajectory of the bench's goal
192 us after 40 ms asleep against 340 (21 against 40 back to back); end to end, three interleaved
runs each, `ratio_p50` 2.11, 2.15 and 2.15 against 2.28, 2.22 and 2.28 (gate p50 0.96 to 1.07 ms
against 1.01 to 1.14, the relay's 0.45 to 0.50 in both).

`ratio_p50` is the gate's median over the relay's; `rejected` counts goals not accepted (the first
reason in `errors`; a rejected goal is not timed), `failed` goals accepted whose result was not
`succeeded`. `goals_met`: `ratio_p50` within 1.5, `p99_ms` within 5 ms, and `nothing_rejected` and
`nothing_failed`, without which the figures are those of the goals that did go through.

With `--viewer`, after that measurement (the baseline, from the same run and stack), the bench
starts `tether view` on the stack's robot, ports and config file (a free loopback port, learnt from
its `--json` line; teleop off, the camera at its default 2 pictures a second to a viewer that
watches it) and connects Foxglove's own WebSocket client to it (@foxglove/ws-protocol under node, the
`subscribe-all` mode of tests/integration/foxglove_client, installed once with `npm ci` into a cache
folder: bench/viewer.py). The client subscribes to every channel the view advertises and reads all
of it, and sends on the same socket `--viewer-garbage-hz` rounds a second (default 20, 0: none) of
garbage frames and bogus client messages (18 frames a round: text that is no JSON, requests with
wrong types or ids that exist nowhere, an advertise the server does not take, binary frames with no
such channel or opcode, 64 KiB of nothing). Once it has received messages, the same goals and plan
checks, interleaved with the relay and the echo in the same way, are measured again while it stays
connected, into `viewer`: `gate_p50_ms`, `gate_p99_ms`, `relay_p50_ms`, `ratio_p50`,
`plan_check_p50_ms`, `plan_check_p99_ms`, `plan_check_echo_p50_ms`, `samples`, `rejected`, `failed`,
`goals_met`, and the client's counts over its whole connection: `messages_received`, `garbage_sent`
(frames), `channels` (subscribed) and `server_statuses` (the server's answers to the garbage).
`viewer` is null without `--viewer`; when node, npm or the client is missing (or `npm ci` fails),
the viewer part is skipped and `viewer_note` (otherwise null) says why; the rest is measured as
usual. Trouble with the viewer part itself goes into `errors`, prefixed "with the viewer:", and
leaves the baseline's results in place.
"""

from __future__ import annotations

import argparse
import math
import random
import tempfile
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bench.service import (
    MAX_N,
    BenchError,
    RobotMotion,
    Stack,
    bench_main,
    bounded,
    measured,
    ms_summary,
    notes,
    print_rows,
    reporter,
    robot_ready,
    show,
)
from bench.transport import bare_echo, raw_echo, timed_pair
from bench.viewer import ViewerMissing, client_script, running_view, running_viewer
from schemas import keys
from schemas.actions import GetResult, GoalResponse, GoalState, SendGoal
from schemas.common import Pose2D
from schemas.incidents import Incident, IncidentKind
from schemas.keys import ActionKeys
from schemas.plan import Action, GroundedPlan, NavigateStep, Plan, PlanApproved, Step
from schemas.robot import (
    ARM_JOINTS,
    GRIPPER_MAX_GAP,
    FollowJointTrajectoryGoal,
    GripperCommandGoal,
    NavigateToPoseGoal,
    TrajectoryPoint,
)
from services import runtime
from services.errors import CallError

PROG = "bench.gate"
GOALS = {"goal_ratio_p50": 1.5, "goal_p99_ms": 5.0}
# At real time the sim thread leaves the CPU (and the GIL) to the goal path, as a robot driver would.
REALTIME_FACTOR = 1.0
CALL_TIMEOUT = 5.0
RESULT_TIMEOUT = 30.0
HOLD_TIME = 0.3  # the trajectory's one point, seconds from start
VIEWER_READY_TIMEOUT = 30.0  # s for the viewer's first messages
GARBAGE_HZ = 20.0
progress = reporter(PROG)


@dataclass(frozen=True)
class GoalKind:
    """A kind of goal that leaves the robot where it is, built from its current state."""

    name: str
    action: ActionKeys[Any, Any, Any]
    goal: Callable[[RobotMotion], Any]


def hold_arm(state: RobotMotion) -> FollowJointTrajectoryGoal:
    joints = state.joints.message
    assert joints is not None
    now = dict(zip(joints.name, joints.position, strict=False))
    point = TrajectoryPoint(positions=[now[name] for name in ARM_JOINTS], time_from_start=HOLD_TIME)
    return FollowJointTrajectoryGoal(joint_names=list(ARM_JOINTS), points=[point])


def stay(state: RobotMotion) -> NavigateToPoseGoal:
    odom = state.odom.message
    assert odom is not None
    return NavigateToPoseGoal(pose=odom.pose)


KINDS = (
    GoalKind("gripper", keys.CMD_GRIPPER, lambda _: GripperCommandGoal(position=GRIPPER_MAX_GAP)),
    GoalKind("trajectory", keys.CMD_TRAJECTORY, hold_arm),
    GoalKind("navigate", keys.CMD_NAVIGATE, stay),
)


@dataclass
class Samples:
    """Round trips in ms by kind, (relay, gate), and goals that did not go through."""

    times: dict[str, tuple[list[float], list[float]]]
    rejected: int = 0
    failed: int = 0
    errors: list[str] = field(default_factory=list)

    def note(self, count: int, what: str) -> None:
        """The first of each kind of trouble goes into the errors."""
        if count == 1:
            self.errors.append(what)
            progress(what)


def one_goal(stack: Stack, state: RobotMotion, kind: GoalKind, i: int) -> tuple[float, float, GoalResponse]:
    """(relay ms, gate ms, the reply) for one send_goal of `kind`, interleaved with the relay."""
    node = stack.node
    request = SendGoal(goal_id=uuid.uuid4().hex, goal=kind.goal(state))
    relay = raw_echo(node, keys.bench_relay_key(node.robot), runtime.encode(request))
    replies: list[GoalResponse] = []

    def gate() -> None:
        replies.append(node.call(kind.action.send_goal, request, timeout=CALL_TIMEOUT))

    try:
        relay_ms, gate_ms = timed_pair(i, relay, gate)
    except RuntimeError as exc:  # the relay failed
        raise BenchError(str(exc)) from None
    except CallError as exc:
        raise BenchError(f"{kind.action.send_goal.path}: {exc.error.message}") from None
    return relay_ms, gate_ms, replies[0]


def finish(stack: Stack, kind: GoalKind, goal_id: str, samples: Samples) -> None:
    """Wait for the goal's result (not timed), so the next goal finds the robot idle."""
    try:
        result = stack.node.call(kind.action.get_result, GetResult(goal_id=goal_id), timeout=RESULT_TIMEOUT)
    except CallError as exc:
        raise BenchError(f"{kind.action.get_result.path}: {exc.error.message}") from None
    if result.state is not GoalState.SUCCEEDED:
        samples.failed += 1
        samples.note(samples.failed, f"a {kind.name} goal ended {result.state}: {result.message}")


def measure(stack: Stack, state: RobotMotion, n: int, warmup: int, max_seconds: float, rate: float) -> Samples:
    samples = Samples({kind.name: ([], []) for kind in KINDS})
    deadline = time.monotonic() + max_seconds
    last_sent = dict.fromkeys(samples.times, -math.inf)
    for i in range((warmup + n) * len(KINDS)):
        kind = KINDS[i % len(KINDS)]
        relay, gate = samples.times[kind.name]
        if time.monotonic() > deadline and len(gate) >= 10:
            progress(f"stopped after {max_seconds:g} s")
            break
        time.sleep(max(0.0, last_sent[kind.name] + 1.0 / rate - time.monotonic()))
        last_sent[kind.name] = time.monotonic()
        # Each kind alternates which goes first from one round to the next.
        relay_ms, gate_ms, reply = one_goal(stack, state, kind, i // len(KINDS))
        if not reply.accepted:
            samples.rejected += 1
            samples.note(samples.rejected, f"a {kind.name} goal was rejected: {reply.reason}")
            continue
        finish(stack, kind, reply.goal_id, samples)
        if i >= warmup * len(KINDS):
            relay.append(relay_ms)
            gate.append(gate_ms)
    return samples


def seed_incidents(path: Path, count: int, seed: int = 19) -> None:
    """`count` incidents at random points of the household flat's rooms, one kind after another."""
    from services.safety.incidents import seed as write
    from services.worldmodel import load_world

    world = load_world("household")
    boxes = [
        (min(xs), min(ys), max(xs), max(ys)) for room in world.rooms for xs, ys in [zip(*room.polygon, strict=True)]
    ]
    rng = random.Random(seed)
    kinds = list(IncidentKind)

    def one(i: int) -> Incident:
        x0, y0, x1, y1 = boxes[i % len(boxes)]
        x, y = rng.uniform(x0, x1), rng.uniform(y0, y1)
        return Incident(id=i, stamp=1e9 + i, kind=kinds[i % len(kinds)], reason="bench", x=x, y=y)

    write(path, (one(i) for i in range(1, count + 1)))


def plan_checks(stack: Stack, state: RobotMotion, n: int) -> tuple[list[float], list[float], int]:
    """(echo ms, check ms, warnings in the last reply) for `n` checks of a plan to where the robot stands,
    each interleaved with safety's bare echo: safety answers the check itself, with no hop to the robot."""
    node = stack.node
    odom = state.odom.message
    assert odom is not None
    here = Pose2D(x=odom.pose.x, y=odom.pose.y, yaw=odom.pose.yaw)
    source = Plan(steps=[Step(action=Action.NAVIGATE_TO, target="here")])
    grounded = GroundedPlan(steps=[NavigateStep(target="here", goal=here)], source=source)
    payload = runtime.encode(grounded)
    echo_ms: list[float] = []
    check_ms: list[float] = []
    warnings = 0
    replies: list[Any] = []
    echo = bare_echo(node, payload, "safety")

    def check() -> None:
        replies.append(node.call(keys.PLAN_CHECK, grounded, timeout=CALL_TIMEOUT))

    for i in range(n):
        replies.clear()
        try:
            e, c = timed_pair(i, echo, check)
        except RuntimeError as exc:  # the echo failed
            raise BenchError(str(exc)) from None
        except CallError as exc:
            raise BenchError(f"{keys.PLAN_CHECK.path}: {exc.error.message}") from None
        if not isinstance(replies[0], PlanApproved):
            raise BenchError(f"the plan check refused a plan to where the robot stands: {replies[0]}")
        warnings = len(replies[0].warnings)
        echo_ms.append(e)
        check_ms.append(c)
    return echo_ms, check_ms, warnings


def summarize(samples: Samples) -> dict[str, Any]:
    everything = [[ms for k in KINDS for ms in samples.times[k.name][j]] for j in (0, 1)]
    if not everything[1]:
        raise BenchError(f"no goal went through the gate ({samples.rejected} rejected)")
    r50, r99 = ms_summary(everything[0])
    g50, g99 = ms_summary(everything[1])
    kinds: dict[str, Any] = {}
    for name, (relay, gate) in samples.times.items():
        if gate:
            p50, p99 = ms_summary(gate)
            kinds[name] = {"p50_ms": p50, "p99_ms": p99, "relay_p50_ms": ms_summary(relay)[0], "samples": len(gate)}
    return {
        "gate_p50_ms": g50,
        "gate_p99_ms": g99,
        "relay_p50_ms": r50,
        "relay_p99_ms": r99,
        "ratio_p50": round(g50 / r50, 3),
        "samples": len(everything[1]),
        "kinds": kinds,
        # With goals rejected (not timed) or failed, the figures are not those of goals that all went through.
        "goals_met": {
            "ratio_p50": g50 / r50 <= GOALS["goal_ratio_p50"],
            "p99_ms": g99 <= GOALS["goal_p99_ms"],
            "nothing_rejected": samples.rejected == 0,
            "nothing_failed": samples.failed == 0,
        },
    }


def with_viewer(stack: Stack, state: RobotMotion, script: Path, args: argparse.Namespace) -> dict[str, Any]:
    """The goals and plan checks again, while Foxglove's client, subscribed to everything (and sending
    garbage), is connected to `tether view` on the stack."""
    n, warmup = args.n, args.warmup
    logs = stack.supervisor.log_dir
    with (
        running_view(stack, progress) as (url, view, _),
        running_viewer(script, url, args.viewer_garbage_hz, logs / "viewer.log", progress) as viewer,
    ):
        first = viewer.wait_flowing(VIEWER_READY_TIMEOUT)
        progress(
            f"the viewer subscribed to {first['channels']} channels; measuring {n} goals of each kind again "
            f"(+{warmup} warm-up, <= {args.max_seconds:g} s)"
        )
        samples = measure(stack, state, n, warmup, args.max_seconds, args.goals_per_second)
        progress(f"measuring {n} plan checks again")
        echoes, checks, _ = plan_checks(stack, state, n + warmup)
        if view.poll() is not None:
            raise BenchError(f"tether view exited with code {view.returncode} during the measurement")
        counts = viewer.stop()
    progress(f"the viewer received {counts['messages']} messages and sent {counts['garbage']} garbage frames")
    summary = summarize(samples)
    c50, c99 = ms_summary(checks[warmup:])
    errors = [f"with the viewer: {error}" for error in samples.errors]
    if counts["done"] != "stdin":
        errors.append(f"with the viewer: its connection ended before the measurement did ({counts['done']})")
    return {
        "gate_p50_ms": summary["gate_p50_ms"],
        "gate_p99_ms": summary["gate_p99_ms"],
        "relay_p50_ms": summary["relay_p50_ms"],
        "ratio_p50": summary["ratio_p50"],
        "plan_check_p50_ms": c50,
        "plan_check_p99_ms": c99,
        "plan_check_echo_p50_ms": ms_summary(echoes[warmup:])[0],
        "samples": summary["samples"],
        "rejected": samples.rejected,
        "failed": samples.failed,
        "goals_met": summary["goals_met"],
        "messages_received": counts["messages"],
        "garbage_sent": counts["garbage"],
        "channels": counts["channels"],
        "server_statuses": counts["statuses"],
        "errors": errors,
    }


def bench(args: argparse.Namespace, viewer_script: Path | None) -> dict[str, Any]:
    n, warmup, max_seconds = args.n, args.warmup, args.max_seconds
    sim = {"realtime_factor": args.realtime_factor, "objects_hz": args.objects_hz}
    with tempfile.TemporaryDirectory(prefix="bench-gate-incidents-") as tmp:
        safety: dict[str, Any] = {}
        if args.incidents:
            store = Path(tmp) / "incidents.sqlite"
            progress(f"writing {args.incidents} incidents into safety's store {store}")
            seed_incidents(store, args.incidents)
            safety["incident_store"] = str(store)
        with robot_ready("gate", progress, sim, arm=True, safety=safety) as (stack, state, _):
            progress(f"measuring {n} goals of each kind against the relay (+{warmup} warm-up, <= {max_seconds:g} s)")
            samples = measure(stack, state, n, warmup, max_seconds, args.goals_per_second)
            progress(f"measuring {n} plan checks against safety's echo")
            echoes, checks, warnings = plan_checks(stack, state, n + warmup)
            viewed: dict[str, Any] | None = None
            if viewer_script is not None:
                try:
                    viewed = with_viewer(stack, state, viewer_script, args)
                except BenchError as exc:  # the baseline stands
                    samples.errors.append(f"with the viewer: {exc}")
                    progress(f"error: with the viewer: {exc}")
    c50, c99 = ms_summary(checks[warmup:])
    if viewed is not None:
        samples.errors += viewed.pop("errors")
    return {
        **summarize(samples),
        "plan_check_p50_ms": c50,
        "plan_check_p99_ms": c99,
        "plan_check_echo_p50_ms": ms_summary(echoes[warmup:])[0],
        "plan_check_warnings": warnings,
        "incidents": args.incidents,
        "rejected": samples.rejected,
        "failed": samples.failed,
        "errors": samples.errors,
        "viewer": viewed,
    }


def viewer_client(args: argparse.Namespace) -> tuple[Path | None, str | None]:
    """(the Foxglove client's script, None) with --viewer, (None, why not) when it cannot run, (None, None) without."""
    if not args.viewer:
        return None, None
    try:
        return client_script(), None
    except (ViewerMissing, BenchError) as exc:
        progress(f"the viewer part is skipped: {exc}")
        return None, str(exc)


def run(args: argparse.Namespace) -> dict[str, Any]:
    script, viewer_note = viewer_client(args)
    defaults: dict[str, Any] = {
        "gate_p50_ms": None,
        "gate_p99_ms": None,
        "relay_p50_ms": None,
        "relay_p99_ms": None,
        "ratio_p50": None,
        "samples": 0,
        "kinds": {},
        **GOALS,
        "plan_check_p50_ms": None,
        "plan_check_p99_ms": None,
        "plan_check_echo_p50_ms": None,
        "plan_check_warnings": 0,
        "incidents": args.incidents,
        "rejected": 0,
        "failed": 0,
        "warmup": args.warmup,
        "viewer": None,
        "viewer_note": viewer_note,
    }
    result = measured(defaults, lambda: bench(args, script), progress)
    result["notes"] = notes(
        gate="send_goal on cmd/<action> to safety: decode, e-stop and policy checks, a safety event, then "
        "send_goal on robot/<action> to the sim (signed, checked there) and its reply back; safety serves it "
        "on a kept worker thread (services/querypool.py), the sim on Zenoh's callback thread (no goal to "
        "preempt), its goal started and both traces published after the replies",
        relay="raw get on bench/raw_relay: safety forwards the bytes with a plain get to the sim's "
        "bench/raw_echo/sim and replies with them; same request bytes as the goal",
        plan_check_echo="raw get on bench/raw_echo/safety, answered by safety itself, as the plan check is; "
        "same request bytes as the check",
        order="interleaved, alternating first call; each goal's result fetched (untimed) before the next",
        goals_per_second_per_kind=args.goals_per_second,
        sim={"realtime_factor": args.realtime_factor, "objects_hz": args.objects_hz},
    )
    if args.viewer:
        result["notes"]["viewer"] = (
            "after the baseline, the same goals and plan checks while tether view (loopback, teleop off) "
            "serves Foxglove's ws-protocol client, subscribed to every channel and reading it all, sending "
            f"{args.viewer_garbage_hz:g} rounds of 18 garbage frames a second on the same socket"
        )
    return result


def pair_of(result: dict[str, Any], prefix: str) -> str:
    return f"{show(result[f'{prefix}_p50_ms'])} / {show(result[f'{prefix}_p99_ms'])}"


def print_table(result: dict[str, Any]) -> None:
    rows = [
        ("gate p50 / p99 ms", pair_of(result, "gate"), f"- / {show(GOALS['goal_p99_ms'])}"),
        ("relay p50 / p99 ms", pair_of(result, "relay"), ""),
        ("ratio p50", show(result["ratio_p50"], "x"), show(GOALS["goal_ratio_p50"], "x")),
        *(
            (f"  {name} p50 / p99 ms", f"{show(k['p50_ms'])} / {show(k['p99_ms'])}", "")
            for name, k in result["kinds"].items()
        ),
        ("rejected / failed goals", f"{result['rejected']} / {result['failed']}", "0 / 0"),
    ]
    if (viewed := result.get("viewer")) is not None:
        rows += [
            ("with a viewer: gate p50 / p99 ms", pair_of(viewed, "gate"), f"- / {show(GOALS['goal_p99_ms'])}"),
            ("with a viewer: relay p50 ms", show(viewed["relay_p50_ms"]), ""),
            ("with a viewer: ratio p50", show(viewed["ratio_p50"], "x"), show(GOALS["goal_ratio_p50"], "x")),
            ("with a viewer: plan check p50 / p99 ms", pair_of(viewed, "plan_check"), ""),
            ("viewer: messages in / garbage out", f"{viewed['messages_received']} / {viewed['garbage_sent']}", ""),
        ]
    elif result.get("viewer_note"):
        rows.append(("with a viewer", f"skipped: {result['viewer_note']}", ""))
    print_rows(f"goals through safety ({result['samples']} samples)", rows, result["errors"])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--n", type=bounded(int, 10, MAX_N), default=200, help="goals of each kind")
    parser.add_argument("--warmup", type=bounded(int, 0, MAX_N), default=20, help="goals of each kind not counted")
    parser.add_argument(
        "--max-seconds", type=bounded(float, 0.0, 600.0, open_low=True), default=180.0, help="stop measuring then"
    )
    parser.add_argument(
        "--goals-per-second",
        type=bounded(float, 0.0, 1000.0, open_low=True),
        default=8.0,
        help="goals of one kind a second at most (safety's default policy allows 10)",
    )
    parser.add_argument(
        "--realtime-factor",
        type=bounded(float, 0.1, 20.0),
        default=REALTIME_FACTOR,
        help="the sim's speed (faster than real time: results come sooner, but physics takes the CPU)",
    )

    parser.add_argument(
        "--incidents",
        type=bounded(int, 0, 1_000_000),
        default=0,
        help="start safety with a memory of this many incidents (0: none)",
    )
    parser.add_argument(
        "--objects-hz",
        type=bounded(float, 0.0, 100.0, open_low=True),
        default=5.0,
        help="the sim's camera rate (frames are rendered in a process of the sim's own)",
    )
    parser.add_argument(
        "--viewer",
        action="store_true",
        help="then measure again while tether view serves a Foxglove client subscribed to everything (needs node)",
    )
    parser.add_argument(
        "--viewer-garbage-hz",
        type=bounded(float, 0.0, 1000.0),
        default=GARBAGE_HZ,
        help="rounds of garbage frames and bogus messages the viewer sends a second (0: none)",
    )


def main(argv: list[str] | None = None) -> None:
    bench_main(PROG, __doc__ or "", add_arguments, run, print_table, argv)


if __name__ == "__main__":
    main()
