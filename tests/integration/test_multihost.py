"""Across hosts in network namespaces, TLS on: link cuts, bad links, crashes and hangs, intruders, two robots.

One deployment (tests/multihost/stack.py) serves the module: the router and the planner side on an
edge host, robot r1's sim, safety and recorder on a host behind a link proxy, robot r2's on another,
the CLI on an operator host. Every check is on what the sim reports (its stamped odometry, its
ground truth), heard through a tap that no fault touches. Tests leave the stack as they found it:
every service alive, the e-stop clear, links whole.
"""

from __future__ import annotations

import json
import math
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from schemas.executor import PlanStatus
from services.runtime import Node
from services.worldmodel import load_world
from tests.multihost import netns
from tests.multihost.intruder import HOLDING, MARKER_NAME, MARKER_SPEED
from tests.multihost.stack import EDGE_SERVICES, ROBOT_SERVICES, STILL, MultiHost, Watch, clean_env, wait_for

pytestmark = [pytest.mark.multihost, pytest.mark.realtime, pytest.mark.alone, pytest.mark.timeout(600)]

# The robots drive between two spots 2 m apart in the kitchen, far from the person in the living
# room (a drive of about 7 sim seconds there, under 2 s at SIM's speed; the first, from the start in
# the living room, about 4 m): each plan with the approach pose it leaves the base at, in the
# default world the deployment runs.
APPROACH = {furniture.name: furniture.approach for furniture in load_world().furniture}
PLANS = {
    json.dumps({"plan": [{"action": "navigate_to", "target": name}]}): APPROACH[name]
    for name in ("kitchen table", "kitchen counter")
}
# The sim four times faster than real time: the drives these tests wait for take a quarter of the
# wall time (the module took about 115 s at real time, 70 s so). What they bound is in wall time and
# unchanged by it: the robot's heartbeat guard, the link's outage, the odometry's rate and stamps.
SIM = {"realtime_factor": 4.0, "odom_hz": 100.0}
HEARTBEAT_TIMEOUT = 0.2  # the sim's default [sim] heartbeat_timeout, which the deployment keeps
SIM_TICK = 1 / 240  # sim s: the default physics_hz; it obeys the heartbeat guard once a step
# What these tests assert a halt against, measured on the sim's stamped odometry from the fault: the
# heartbeat timeout (the guard's), two sim ticks in wall time (the stale guard seen at the next step,
# the base at rest after the one following), one odometry period (the first still sample), and
# scheduling slack for this 2-core machine, loaded by the rest of the suite: the sim's and safety's
# threads may start late. Measured here: 191-271 ms at real time, 97-199 ms at four times. The
# issue's goal, 250 ms, is what bench.partition reports and checks (goals_met); a test failing on a
# goal the machine meets only when idle would be flaky.
SCHEDULING_SLACK = 0.15
HALT_BOUND = HEARTBEAT_TIMEOUT + 2 * SIM_TICK / SIM["realtime_factor"] + 1 / SIM["odom_hz"] + SCHEDULING_SLACK
# A halt is seen once this many odometry samples, all still, followed it (1.5 s at odom_hz).
HALT_SAMPLES = 150
RECOVERY = 10.0  # every service alive again after a link returns
PLAN_TIMEOUT = 180.0
OUTAGE = 3.0  # s the link stays cut: the outage itself, not a wait for anything
# Before each test: a robot's odometry (100 Hz) and safety's heartbeat (50 Hz) arriving for STEADY_FOR
# with no gap over STEADY_GAP, waited for SETTLE_TIMEOUT at most (see settle).
STEADY_FOR = 1.0
STEADY_GAP = 0.1
SETTLE_TIMEOUT = 30.0


@pytest.fixture(scope="module")
def mh(tmp_path_factory: pytest.TempPathFactory) -> Iterator[MultiHost]:
    reason = netns.unavailable()
    if reason is not None:
        pytest.skip(reason)
    netns.sweep_stale()
    stack = MultiHost(tmp_path_factory.mktemp("multihost"), [("r1", "robot"), ("r2", "robot2")], SIM)
    try:
        yield stack
    finally:
        stack.close()


@pytest.fixture
def stack(mh: MultiHost) -> Iterator[MultiHost]:
    """The shared stack, once every robot's odometry and heartbeat come steadily (see settle); its logs'
    tails are printed (and shown if the test failed)."""
    for robot in mh.robots:
        settle(mh, robot)
    yield mh
    mh.print_logs(30)


def settle(mh: MultiHost, robot: str) -> None:
    """Wait (SETTLE_TIMEOUT at most) until `robot`'s odometry and heartbeat have come for STEADY_FOR
    without a gap over STEADY_GAP. Measured while the stacks still started (the first test cut the link a
    second after the robots first heard safety), a halt came once 374 ms after the fault, where 97 to 199 ms
    is usual. Not settled in time, the test goes on."""
    watch = watch_of(mh, robot)
    try:
        wait_for(lambda: watch.steady(time.time() - STEADY_FOR, STEADY_GAP), SETTLE_TIMEOUT, f"{robot} steady")
    except TimeoutError as exc:
        print(f"{exc}; going on")


def watch_of(mh: MultiHost, robot: str = "r1") -> Watch:
    watch = mh.robots[robot].watch
    assert watch is not None
    return watch


def healthy(mh: MultiHost, robot: str, timeout: float) -> float:
    """Seconds until `tether status --check` on the operator host says every service alive and the heartbeat
    fresh; fails after `timeout`."""
    start = time.monotonic()
    last: Any = None
    while time.monotonic() - start < timeout:
        last = mh.cli(robot, "operator", "status", "--check", timeout=30)
        if last.returncode == 0:
            return time.monotonic() - start
    raise AssertionError(f"status --check of {robot} not healthy within {timeout:g} s: {last.stdout}{last.stderr}")


def still_during(watch: Watch, since: float, until: float) -> list[tuple[float, float]]:
    """Samples stamped in [since, until] in which the base moved: (seconds after `since`, speed)."""
    return [(round(s.stamp - since, 3), round(s.speed, 3)) for s in watch.samples(since, until) if s.speed >= STILL]


def halted(watch: Watch, t0: float) -> bool:
    """The base came to rest after `t0` and HALT_SAMPLES still samples have followed."""
    halt = watch.halt_after(t0)
    return halt is not None and len(watch.samples(since=t0 + halt)) >= HALT_SAMPLES


def halted_within(watch: Watch, t0: float, until: float, what: str) -> float:
    """The halt after `t0` measured on the sim's stamped odometry (samples up to `until`), checked and printed."""
    wait_for(lambda: watch.samples(since=until), 20.0, f"odometry stamped after {what} ended")
    halt = watch.halt_after(t0, until)
    assert halt is not None, f"the base never came to rest after {what}: {still_during(watch, t0, until)[-5:]}"
    print(f"{what}: base at rest {halt * 1000:.0f} ms after it (bound {HALT_BOUND * 1000:.0f} ms)")
    assert halt <= HALT_BOUND, f"{what}: the base took {halt * 1000:.0f} ms to stop"
    # And it stayed at rest, sample by sample, as long as the fault lasted.
    assert not still_during(watch, t0 + halt, until)
    assert len(watch.samples(t0 + halt, until)) >= (until - t0 - halt) * 20, "odometry missing while at rest"
    return halt


def after_fault(stack: MultiHost, robot: str) -> None:
    """Safety's own watchdog may have latched the e-stop (no odometry while the base moved): the latch
    holds until an operator resets it, as it should; the operator does, from the operator host."""
    beats = watch_of(stack, robot).beats
    if beats and beats[-1].latched:
        print(f"{robot}: e-stop latched during the fault; the operator resets it")
        stack.reset(robot)


def start_moving(mh: MultiHost, robot: str, plan: str) -> Any:
    handle = mh.send(robot, plan)
    wait_for(watch_of(mh, robot).moving, 60.0, f"{robot} moving on its plan")
    return handle


def succeeded(mh: MultiHost, robot: str, plan: str) -> None:
    run = mh.result(robot, mh.send(robot, plan), PLAN_TIMEOUT)
    assert run.result is not None
    assert run.result.status is PlanStatus.SUCCEEDED, run.result.reason


def away(mh: MultiHost, robot: str) -> str:
    """The plan whose end is farther from where `robot` stands now, so that it surely drives."""
    pose = mh.truth(robot).robot
    return max(PLANS, key=lambda plan: math.hypot(pose.x - PLANS[plan].x, pose.y - PLANS[plan].y))


def test_a_cut_link_halts_the_robot_within_the_watchdog_bound_and_the_stack_recovers(stack: MultiHost) -> None:
    watch = watch_of(stack)
    handle = start_moving(stack, "r1", away(stack, "r1"))
    t0 = stack.topo.cut("robot")
    time.sleep(OUTAGE)
    t1 = stack.topo.restore("robot")

    halted_within(watch, t0, t1, "the robot-edge link cut")
    run = stack.result("r1", handle, PLAN_TIMEOUT)
    assert run.result is not None and run.result.status is PlanStatus.FAILED, run.result
    assert "heartbeat" in run.result.reason, run.result.reason  # the lost link, as the robot saw it

    missing = stack.wait_alive("r1", RECOVERY)
    assert not missing, f"not alive {RECOVERY:g} s after the link returned: {missing}"
    print(f"every service healthy {healthy(stack, 'r1', RECOVERY):.2f} s after the link returned")
    after_fault(stack, "r1")
    start = stack.truth("r1").robot
    succeeded(stack, "r1", away(stack, "r1"))
    end = stack.truth("r1").robot
    assert math.hypot(end.x - start.x, end.y - start.y) > 0.5, "the new plan's success moved the robot"


def test_b_a_slow_stalling_link_and_a_narrow_one_never_let_the_robot_move_unchecked(stack: MultiHost) -> None:
    watch = watch_of(stack)
    link = stack.robots["r1"].link
    assert link is not None
    outcomes = []
    try:
        for shape in ("delayed", "narrow"):
            if shape == "delayed":
                link.delay(200)
            else:
                link.delay(0)
                stack.topo.narrow("robot", rate="1mbit", burst="32kb", latency="200ms")
            after_fault(stack, "r1")
            plan = away(stack, "r1")
            handle = start_moving(stack, "r1", plan)
            stall = link.stall(1.2)
            wait_for(lambda s=stall: time.time() > s["stall_until"], 5.0, "the stall's end")
            halted_within(watch, stall["stall_from"], stall["stall_until"], f"a 1.2 s stall on the {shape} link")
            run = stack.result("r1", handle, PLAN_TIMEOUT)
            assert run.result is not None
            status, reason = run.result.status, run.result.reason
            outcomes.append((shape, str(status), reason))
            assert status in (PlanStatus.SUCCEEDED, PlanStatus.FAILED), (shape, status, reason)
            assert status is PlanStatus.SUCCEEDED or reason, "a failed plan says why"
    finally:
        link.delay(0)
        stack.topo.widen("robot")
    print("plans on the bad links:", outcomes)
    after_fault(stack, "r1")
    last = watch.samples()[-1]
    assert last.speed < STILL, "the robot is at rest once its plans ended"
    healthy(stack, "r1", RECOVERY)


def sigkill(stack: MultiHost, service: str) -> None:
    os.kill(stack.service_pid("r1", service), signal.SIGKILL)


def test_c_router_killed_services_killed_and_hung_the_stack_recovers_and_nothing_moves_unchecked(
    stack: MultiHost,
) -> None:
    watch = watch_of(stack)
    assert stack.router is not None
    # The router killed and started again: every client finds it again by itself.
    stack.topo.signal(stack.router, signal.SIGKILL)
    stack.router.popen.wait(10)
    stack.start_router()
    for robot in ("r1", "r2"):
        missing = stack.wait_alive(robot, 30.0)
        assert not missing, f"{robot} after the router's restart: {missing}"
        print(f"{robot} healthy {healthy(stack, robot, 30.0):.2f} s after every service was seen alive")

    # Safety killed, then hung (SIGSTOP), each while the robot drives: it halts on the missing heartbeat.
    for fault in ("SIGKILL", "SIGSTOP"):
        after_fault(stack, "r1")
        handle = start_moving(stack, "r1", away(stack, "r1"))
        pid = stack.service_pid("r1", "safety")
        t0 = time.time()
        os.kill(pid, getattr(signal, fault))
        wait_for(lambda t0=t0: halted(watch, t0), 20.0, f"the base at rest for {HALT_SAMPLES} samples")
        until = time.time()
        if fault == "SIGSTOP":
            os.kill(pid, signal.SIGCONT)
        halt = watch.halt_after(t0, until)
        assert halt is not None and halt <= HALT_BOUND, f"safety {fault}: halt {halt}"
        assert not still_during(watch, t0 + halt, until - 0.5)
        print(f"safety {fault}: base at rest {halt * 1000:.0f} ms after it")
        run = stack.result("r1", handle, PLAN_TIMEOUT)
        # The attempt under way when safety went is lost; the executor may retry the step, and the retry
        # reaches a safety that is back (restarted, or continued) and checks it afresh.
        assert run.result is not None, run
        if run.result.status is PlanStatus.SUCCEEDED:
            assert run.result.steps[0].attempts > 1, f"the attempt that lost safety succeeded: {run.result}"
        healthy(stack, "r1", 30.0)

    # Every other service killed at once, then every one hung at once for 2 s: the stack comes back.
    for service in (*ROBOT_SERVICES, *EDGE_SERVICES):
        if service != "safety":
            sigkill(stack, service)
    print(f"healthy {healthy(stack, 'r1', 60.0):.2f} s after every other service was SIGKILLed")
    pids = [stack.service_pid("r1", s) for s in (*ROBOT_SERVICES, *EDGE_SERVICES)]
    t0 = time.time()
    for pid in pids:
        os.kill(pid, signal.SIGSTOP)
    time.sleep(2.0)  # the hang itself
    for pid in pids:
        os.kill(pid, signal.SIGCONT)
    print(f"healthy {healthy(stack, 'r1', 30.0):.2f} s after every service was continued")
    assert watch.samples()[-1].speed < STILL
    after_fault(stack, "r1")
    succeeded(stack, "r1", away(stack, "r1"))


def intruder(stack: MultiHost, config: Path, robot: str, *attempts: str, token: Path | None = None) -> list[str]:
    """The intruder's command line, run on the operator host (tests/multihost/intruder.py)."""
    netns_exec = ["ip", "netns", "exec", stack.topo.host("operator").netns]
    argv = [*netns_exec, sys.executable, "-m", "tests.multihost.intruder", "--config", str(config), "--robot", robot]
    return [*argv, *(["--token-file", str(token)] if token else []), *attempts]


def intrude(stack: MultiHost, config: Path, robot: str, *attempts: str, token: Path | None = None) -> dict[str, Any]:
    argv = intruder(stack, config, robot, *attempts, token=token)
    done = subprocess.run(argv, env=clean_env(), capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    result: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


# How long the services seen alive are watched while an intruder holds forged tokens, at most.
FORGED_WATCH = 2.0


def alive_while_forged(stack: MultiHost, node: Node, config: Path, robot: str, until_seen: str = "") -> set[str]:
    """The services `node` sees alive while an intruder with identity `config` holds alive/safety and
    alive/sim tokens for `robot`: from when it holds them, for FORGED_WATCH seconds or until
    `until_seen` is among them."""
    argv = intruder(stack, config, robot, "alive")
    with subprocess.Popen(argv, env=clean_env(), stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True) as proc:
        assert proc.stdin is not None and proc.stdout is not None
        try:
            ready, _, _ = select.select([proc.stdout], [], [], 60.0)
            line = proc.stdout.readline().strip() if ready else ""
            assert line == HOLDING, f"the intruder did not hold its tokens: {line or 'no answer within 60 s'}"
            # Asked again and again: a token let through reaches the router a moment after it is declared.
            seen: set[str] = set()
            until = time.monotonic() + FORGED_WATCH
            while time.monotonic() < until and until_seen not in seen:
                seen |= node.alive_services()
            proc.stdin.close()  # the intruder lets go of its tokens and ends
            assert proc.wait(timeout=60.0) == 0, "the intruder failed"
            return seen
        finally:
            if proc.poll() is None:
                proc.kill()  # then waited for as the with ends


def test_d_the_agent_robot2_and_strangers_are_refused_and_the_robot_does_not_move(stack: MultiHost) -> None:
    watch = watch_of(stack)
    node = watch.node
    heard: list[bytes] = []
    node.subscribe_raw("tether/r1/robot/cmd_vel", lambda _k, raw: heard.append(raw))
    node.subscribe_raw("tether/r1/world/humans", lambda _k, raw: heard.append(raw))
    token = stack.deploy / "r1" / "operator.token"
    before = stack.truth("r1").robot

    # The agent may stop the robot (a positive control: the same session gets through where allowed) ...
    agent = stack.deploy / "r1" / "agent.json5"
    asked = time.time()
    stopped = stack.cli("r1", "agent", "estop", "--reason", "agent test")
    assert stopped.returncode == 0, stopped.stdout + stopped.stderr
    wait_for(lambda: any(b.arrived > asked and b.latched for b in watch.beats), 10.0, "the agent's e-stop latched")
    # ... but not reset it, even holding the operator's token, nor command the robot or invent people.
    refused = stack.cli("r1", "agent", "reset", "--token-file", str(token))
    assert refused.returncode != 0, refused.stdout
    tried = intrude(stack, agent, "r1", "cmd_vel", "navigate", "reset", "humans", token=token)
    assert tried["opened"], tried
    assert tried["navigate"]["replies"] == 0 and tried["reset"]["replies"] == 0, tried
    assert watch.beats[-1].latched, "the e-stop is still latched after the agent's resets"

    # robot2's identities against robot1, with robot1's unlatched so that anything let through would move it.
    stack.reset("r1")
    for identity in ("safety", "operator", "agent"):
        tried = intrude(stack, stack.deploy / "r2" / f"{identity}.json5", "r1", "cmd_vel", "navigate", "reset",
                        token=token)  # fmt: skip
        assert tried["opened"], tried
        assert tried["navigate"]["replies"] == 0 and tried["reset"]["replies"] == 0, (identity, tried)

    # A session with no credentials and no certificate, over TLS and over plain TCP; the positive
    # control first: the same listen with r1's operator identity hears r1 (its heartbeat at least),
    # so a stranger's silence below is the router's refusal, not a listener that hears nothing.
    allowed = intrude(stack, stack.deploy / "r1" / "operator.json5", "r1", "listen")
    assert allowed["opened"] and allowed["listen"]["heard"] > 0, allowed
    stranger = stack.workdir / "stranger"
    stranger.mkdir(exist_ok=True)
    conf = {"mode": "client", "connect": {"endpoints": []}, "scouting": {"multicast": {"enabled": False}}}
    for endpoint in (f"tls/{netns.ROUTER_IP}:{netns.ROUTER_PORT}", f"tcp/{netns.ROUTER_IP}:{netns.ROUTER_PORT}"):
        conf["connect"] = {"endpoints": [endpoint]}
        if endpoint.startswith("tls"):
            (stranger / "ca.pem").write_bytes((stack.deploy / "r1" / "ca.pem").read_bytes())
            conf["transport"] = {"link": {"tls": {"root_ca_certificate": "ca.pem"}}}
        path = stranger / f"{endpoint.split('/')[0]}.json5"
        path.write_text(json.dumps(conf))
        tried = intrude(stack, path, "r1", "listen", "cmd_vel")
        assert not tried["opened"] or (tried["listen"]["heard"] == 0), (endpoint, tried)
        print(f"no credentials over {endpoint}: {tried.get('error', tried)}")

    # A forged liveliness token: safety is taken away (its supervisor held, so it stays down) and the
    # agent declares alive/safety; nobody sees it.
    up = stack.robots["r1"].on_robot
    assert up is not None
    stack.topo.signal(up, signal.SIGSTOP)
    try:
        sigkill(stack, "safety")
        wait_for(lambda: "safety" not in node.alive_services(), 15.0, "safety's token gone")
        # Looked for while the agent holds them (asked after, they were gone whatever the router did).
        # The positive control first: safety's own identity may declare alive/safety, and is seen to.
        control = alive_while_forged(stack, node, stack.deploy / "r1" / "safety.json5", "r1", until_seen="safety")
        assert "safety" in control, f"safety's own identity's alive/safety was not seen within {FORGED_WATCH} s"
        seen = alive_while_forged(stack, node, agent, "r1")
        assert "safety" not in seen, "the agent's forged alive/safety reached the router's others"
        assert "executor" in seen, f"the node saw none of the live services either: {seen}"
    finally:
        stack.topo.signal(up, signal.SIGCONT)

    ours = [raw for raw in heard if str(MARKER_SPEED).encode() in raw or MARKER_NAME.encode() in raw]
    assert not ours, f"the router passed on {len(ours)} forged messages"
    after = stack.truth("r1").robot
    assert math.hypot(after.x - before.x, after.y - before.y) < 0.01, "the robot moved"
    assert not stack.wait_alive("r1", 30.0)
    stack.reset("r1")
    healthy(stack, "r1", 30.0)


def test_e_two_robots_on_one_router_run_plans_at_once_isolated(stack: MultiHost) -> None:
    for robot in ("r1", "r2"):
        after_fault(stack, robot)
    other: list[str] = []
    # r1's operator may not hear r2's robot at all.
    stack.robots["r1"].node.subscribe_raw("tether/r2/**", lambda key, _raw: other.append(key))
    starts = {robot: stack.truth(robot).robot for robot in ("r1", "r2")}
    plans = {robot: away(stack, robot) for robot in ("r1", "r2")}
    handles = {robot: stack.send(robot, plans[robot]) for robot in ("r1", "r2")}
    for robot, handle in handles.items():
        run = stack.result(robot, handle, PLAN_TIMEOUT)
        assert run.result is not None and run.result.status is PlanStatus.SUCCEEDED, (robot, run.result)
        end = stack.truth(robot).robot
        start = starts[robot]
        assert math.hypot(end.x - start.x, end.y - start.y) > 0.5, f"{robot} did not move in its own sim"
    assert not other, f"r1's operator heard r2's keys: {sorted(set(other))[:5]}"
