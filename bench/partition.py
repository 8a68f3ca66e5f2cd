"""The robot's link to the edge cut mid-motion, across hosts: the halt, and the time until the stack is whole again.

    python -m bench.partition --json      one JSON object on stdout, progress on stderr
    python -m bench.partition             a short table

Needs root (network namespaces); without it the JSON's `errors` says so. The deployment is the one
tests/integration/test_multihost.py runs (tests/multihost/stack.py): `tether deploy init --tls`, the
router and the planner side on an edge host, robot r1's sim, safety and recorder on a robot host
whose veth joins the edge's bridge, each service logged in as itself; this process watches through
a tap straight into the edge, which no cut touches.

Measured, in each trial: a navigate plan (to the kitchen table or back to the coffee table) is sent;
once odometry shows the base faster than 0.1 m/s, t0 = time.time() and the robot host's veth is taken
down (`ip link set eth0 down`: no carrier, packets vanish, no one is told). Safety's heartbeat then
stops reaching the sim, which stops the base on its own. After `--outage` seconds the link is brought
up (t1) and what the sim published meanwhile arrives here late, with its stamps (a cut shorter than
Zenoh's 10 s lease keeps the sessions). The halt is the first odometry sample stamped after t0 from
which on every sample up to t1 is below 0.01 m/s and rad/s. The recovery is the time from t1 until
every service's liveliness token is present and a heartbeat newer than t1 has arrived (what `tether
status --check` asks). Safety's own watchdog may latch the e-stop meanwhile (no odometry while the
base moved); the operator resets it between trials, as a person would.

Baselines from the same run and topology: `timeout_ms`, the sim's heartbeat_timeout (a halt cannot
come before the last beat is that old), and the halt after a SIGKILL of safety on the robot host
while the base moves (as bench.watchdog, here through the router), safety then restarted by its
`tether up`.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.service import BenchError, bench_main, bounded, measured, notes, print_rows, reporter, show
from bench.transport import percentile

PROG = "bench.partition"
GOALS = {"goal_ms": 250.0, "recover_goal_ms": 10_000.0}
SIM = {"realtime_factor": 1.0, "odom_hz": 250.0}
HEARTBEAT_TIMEOUT_MS = 200.0  # the sim's default heartbeat_timeout, which `tether deploy init` keeps
FAR_PLAN = json.dumps({"plan": [{"action": "navigate_to", "target": "kitchen table"}]})
BACK_PLAN = json.dumps({"plan": [{"action": "navigate_to", "target": "coffee table"}]})
START = (6.0, 1.2)  # the robot's start pose, near the coffee table
MOVE_TIMEOUT = 60.0
RECOVER_TIMEOUT = 60.0
PLAN_TIMEOUT = 180.0
# A halt counts as seen once this many odometry samples, all still, followed it (0.2 s at odom_hz).
HALT_SAMPLES = 50
HALT_TIMEOUT = 10.0
progress = reporter(PROG)


def stats(ms: list[float]) -> dict[str, float | None]:
    if not ms:
        return {"p50_ms": None, "p99_ms": None, "max_ms": None}
    return {
        "p50_ms": round(statistics.median(ms), 2),
        "p99_ms": round(percentile(ms, 99), 2),
        "max_ms": round(max(ms), 2),
    }


def bench(trials: int, kills: int, outage: float) -> dict[str, Any]:
    from tests.multihost import netns
    from tests.multihost.stack import MultiHost, wait_for

    reason = netns.unavailable()
    if reason is not None:
        raise BenchError(reason)
    netns.sweep_stale()
    with tempfile.TemporaryDirectory(prefix="bench-partition-") as tmp:
        progress("starting the deployment across namespaces")
        try:
            mh = MultiHost(Path(tmp), [("r1", "robot")], SIM)
        except (AssertionError, RuntimeError, TimeoutError, OSError) as exc:
            raise BenchError(f"the deployment did not start: {exc}") from None
        try:
            watch = mh.robots["r1"].watch
            assert watch is not None

            def moving() -> Any:
                if watch.beats and watch.beats[-1].latched:
                    mh.reset("r1")
                pose = mh.truth("r1").robot
                far = abs(pose.x - START[0]) + abs(pose.y - START[1]) < 1.5
                handle = mh.send("r1", FAR_PLAN if far else BACK_PLAN)
                wait_for(watch.moving, MOVE_TIMEOUT, "the base moving on its plan")
                return handle

            def halted(t0: float) -> bool:
                """The base came to rest after `t0` and HALT_SAMPLES still samples have followed."""
                seconds = watch.halt_after(t0)
                return seconds is not None and len(watch.samples(since=t0 + seconds)) >= HALT_SAMPLES

            def halt(t0: float, until: float, what: str) -> float:
                wait_for(lambda: watch.samples(since=until), 20.0, f"odometry stamped after {what}")
                seconds = watch.halt_after(t0, until)
                if seconds is None:
                    raise BenchError(f"the base did not come to rest after {what}")
                return round(seconds * 1000, 2)

            halts, recoveries, reasons = [], [], []
            for i in range(trials):
                handle = moving()
                t0 = mh.topo.cut("robot")
                time.sleep(outage)  # the outage itself
                t1 = mh.topo.restore("robot")
                wait_for(lambda t1=t1: fresh(mh, watch, t1), RECOVER_TIMEOUT, "every service and a heartbeat back")
                recoveries.append(round((time.time() - t1) * 1000, 1))
                halts.append(halt(t0, t1, "the cut"))
                run = mh.result("r1", handle, PLAN_TIMEOUT)
                reasons.append(run.result.reason if run.result else "no result")
                progress(
                    f"cut {i + 1}/{trials}: halted {halts[-1]:.1f} ms after it, whole again {recoveries[-1]:.0f} ms"
                )
            killed = []
            for i in range(kills):
                handle = moving()
                pid = mh.service_pid("r1", "safety")
                t0 = time.time()
                os.kill(pid, signal.SIGKILL)
                wait_for(lambda t0=t0: halted(t0), HALT_TIMEOUT, f"the base at rest for {HALT_SAMPLES} samples")
                killed.append(halt(t0, time.time(), "the kill"))
                mh.result("r1", handle, PLAN_TIMEOUT)
                wait_for(lambda: fresh(mh, watch, time.time() - 0.1), RECOVER_TIMEOUT, "safety back")
                progress(f"kill {i + 1}/{kills}: halted {killed[-1]:.1f} ms after it")
        except (AssertionError, TimeoutError, LookupError, OSError) as exc:
            mh.print_logs(20)
            raise BenchError(f"a trial did not complete: {exc}") from None
        finally:
            mh.close()
    return {
        "halt": stats(halts),
        "halts_ms": halts,
        "recover": stats(recoveries),
        "recoveries_ms": recoveries,
        "plan_reasons": sorted(set(reasons)),
        "kill_halt": stats(killed),
        "kill_halts_ms": killed,
        "timeout_ms": HEARTBEAT_TIMEOUT_MS,
        "ratio": round(statistics.median(halts) / statistics.median(killed), 3) if killed else None,
        "trials": len(halts),
        "goals_met": {
            "halt_max_ms": max(halts) <= GOALS["goal_ms"],
            "recover_max_ms": max(recoveries) <= GOALS["recover_goal_ms"],
        },
    }


def fresh(mh: Any, watch: Any, since: float) -> bool:
    """Every service of r1 alive and a heartbeat heard after `since`: what `tether status --check` asks."""
    return bool(watch.fresh_beat(since)) and not mh.wait_alive("r1", 0.5)


def run(args: argparse.Namespace) -> dict[str, Any]:
    defaults: dict[str, Any] = {
        "halt": stats([]),
        "halts_ms": [],
        "recover": stats([]),
        "recoveries_ms": [],
        "kill_halt": stats([]),
        "kill_halts_ms": [],
        "timeout_ms": HEARTBEAT_TIMEOUT_MS,
        "trials": 0,
        **GOALS,
    }
    # The processes' log tails go to stderr, never into the JSON on stdout.
    with contextlib.redirect_stdout(sys.stderr):
        result = measured(defaults, lambda: bench(args.trials, args.kills, args.outage), progress)
    result["notes"] = notes(
        trial=f"navigate plan; robot host's veth down once odometry shows > 0.1 m/s, up after {args.outage:g} s; "
        "halt at the first sim-stamped odometry sample from which all are below 0.01 m/s and rad/s until the "
        "link returned; recovery: link up to every liveliness token and a new heartbeat",
        baseline="timeout_ms: the sim's heartbeat_timeout; kill_halt: SIGKILL of safety on the same topology; "
        "ratio: halt p50 / kill_halt p50",
        topology="edge (router, parser, resolver, executor, planner), robot (sim, safety, recorder); TLS, "
        "one identity per service; network namespaces and a veth pair on 169.254.0.0/16",
        sim=SIM,
    )
    return result


def print_table(result: dict[str, Any]) -> None:
    rows = [
        ("halt p50 ms", show(result["halt"]["p50_ms"]), ""),
        ("halt max ms", show(result["halt"]["max_ms"]), f"<= {show(GOALS['goal_ms'])}"),
        ("whole again p50 ms", show(result["recover"]["p50_ms"]), ""),
        ("whole again max ms", show(result["recover"]["max_ms"]), f"<= {show(GOALS['recover_goal_ms'])}"),
        ("safety SIGKILL halt p50 ms (baseline)", show(result["kill_halt"]["p50_ms"]), ""),
        ("heartbeat timeout ms (baseline)", show(result["timeout_ms"]), ""),
    ]
    print_rows(f"robot-edge link cut mid-motion ({result['trials']} trials)", rows, result["errors"])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--trials", type=bounded(int, 1, 50), default=5, help="link cuts")
    parser.add_argument("--kills", type=bounded(int, 0, 50), default=3, help="SIGKILLs of safety (the baseline)")
    parser.add_argument("--outage", type=bounded(float, 1.0, 8.0), default=2.0, help="seconds each cut lasts")


def main(argv: list[str] | None = None) -> None:
    bench_main(PROG, __doc__ or "", add_arguments, run, print_table, argv)


if __name__ == "__main__":
    main()
