"""The whole stack's resident memory after the demo, each service as it reports itself, against a bare Zenoh process.

    python -m bench.memory --json        one JSON object on stdout, progress on stderr
    python -m bench.memory               a short table with the goal

Measured: every service of `tether up` (sim, safety, parser, resolver, executor, recorder, planner)
started by the Supervisor as `python -m tether run SERVICE`, on a robot name and ports of its own,
with the sim at `--sim-speed` and the recorder writing into a temporary directory. Once all are alive
and the sim reports odometry, each service's memory is read as `tether status` reads it: a query on
`_process/*` that every service answers about itself (services/procstat.py: VmRSS, VmHWM); that is
`after_start`. Then the demo plan (tether.cli.DEMO_PLAN: the red cup to the coffee table) runs to its
end, and the figures are read again, `--samples` times `--interval` s apart; each service's figure is
the median of its samples (`rss_mb`), with the most it ever held (`peak_rss_mb`). The processes a
service started itself (the sim's camera renderer) are read from /proc (`children`). `total_rss_mb`
sums the medians and the children: the goal is at most GOAL_TOTAL_MB. RSS counts a page shared by several processes
(a library file both safety and the executor map, such as pinocchio's) in each of them; `pss_mb` is
the service's proportional share instead (/proc/PID/smaps_rollup, a page shared by n counting 1/n),
and `total_pss_mb` their sum, closer to what the stack takes from the machine.

Baseline, in the same run, while the stack is up: a bare process (`python -c`, importing only zenoh)
that opens a Zenoh session to the stack's services as a service would (peer, the same endpoints),
waits until it sees their liveliness tokens, and reports its own VmRSS (`baseline_rss_mb`, the median
of `--baseline-runs` such processes): the floor of any process on the stack. `baseline_total_mb` is
that floor times the number of services, and `above_baseline_mb` each service's figure minus it.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.service import (
    READY_TIMEOUT,
    BenchError,
    Latest,
    Progress,
    bench_main,
    bench_settings,
    bounded,
    measured,
    notes,
    print_rows,
    reporter,
    running_stack,
    show,
)
from schemas import keys
from schemas.executor import ExecutePlanGoal, PlanStatus
from schemas.process import ProcessStatus
from services.runtime import ALL_SERVICES, Node, NodeSettings, stack_services
from tether.client import PlanSender

PROG = "bench.memory"
GOAL_TOTAL_MB = 700.0
MB = 1024 * 1024
STATUS_TIMEOUT = 3.0
PLAN_TIMEOUT = 600.0
BASELINE_TIMEOUT = 30.0

# The floor: an interpreter with zenoh and one session to the stack, nothing of tether's.
BASELINE_CHILD = """
import json, sys, time
import zenoh

endpoints, prefix, wanted = json.loads(sys.argv[1])
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("connect/endpoints", json.dumps(endpoints))
with zenoh.open(conf) as session:
    deadline = time.monotonic() + 20
    seen = 0
    while time.monotonic() < deadline:
        seen = sum(1 for r in session.liveliness().get(prefix + "/alive/*", timeout=1.0) if r.ok is not None)
        if seen >= wanted:
            break
    rss = next(int(l.split()[1]) * 1024 for l in open("/proc/self/status") if l.startswith("VmRSS:"))
    print(json.dumps({"rss_bytes": rss, "peers_seen": seen}))
"""


def mb(n: float) -> float:
    return round(n / MB, 1)


def read_processes(node: Node, services: tuple[str, ...]) -> dict[str, ProcessStatus]:
    """Every service's own figures (as `tether status` asks them); BenchError naming those that did not answer."""
    found = node.process_statuses(STATUS_TIMEOUT)
    if missing := [s for s in services if s not in found]:
        raise BenchError(f"no process status from {', '.join(missing)} within {STATUS_TIMEOUT:g} s")
    return found


def proportional(pid: int) -> int | None:
    """A local process's proportional share of memory (Pss: each page shared by n processes counts 1/n),
    from /proc/PID/smaps_rollup; None where there is none."""
    try:
        lines = Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines()
    except OSError:
        return None
    return next((int(line.split()[1]) * 1024 for line in lines if line.startswith("Pss:")), None)


def children(pid: int) -> dict[str, tuple[int, int | None]]:
    """A local process's child processes (the sim's camera renderer): (VmRSS, Pss) bytes by "name pid".
    They belong to the stack's memory as much as the service itself, but no service reports them."""
    try:
        pids = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    except OSError:
        return {}
    found = {}
    for child in pids:
        try:
            status = Path(f"/proc/{child}/status").read_text().splitlines()
            args = Path(f"/proc/{child}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        rss = next((int(line.split()[1]) * 1024 for line in status if line.startswith("VmRSS:")), 0)
        name = next((a.decode().rsplit(".", 1)[-1] for a in args if a.startswith(b"services.")), "child")
        found[f"{name} {child}"] = (rss, proportional(int(child)))
    return found


def baseline(settings: NodeSettings, services: tuple[str, ...]) -> dict[str, Any]:
    """One bare Zenoh process on the stack: its VmRSS once it sees every service's liveliness."""
    endpoints = [settings.endpoint(s) for s in ALL_SERVICES]
    args = json.dumps([endpoints, f"tether/{settings.robot}", len(services)])
    child = subprocess.run(
        [sys.executable, "-c", BASELINE_CHILD, args],
        capture_output=True,
        text=True,
        timeout=BASELINE_TIMEOUT,
        check=False,
    )
    if child.returncode != 0:
        raise BenchError(f"the baseline process failed: {child.stderr.strip()[-500:]}")
    result: dict[str, Any] = json.loads(child.stdout)
    if result["peers_seen"] < len(services):
        raise BenchError(f"the baseline process saw {result['peers_seen']} of {len(services)} services alive")
    return result


def run_demo(node: Node, progress: Progress) -> dict[str, Any]:
    from tether.cli import DEMO_PLAN

    progress("running the demo plan")
    started = time.monotonic()
    outcome = PlanSender(node).run(ExecutePlanGoal(text=DEMO_PLAN), PLAN_TIMEOUT)
    seconds = round(time.monotonic() - started, 1)
    if outcome.result is None:
        raise BenchError(f"the demo plan has no result after {seconds} s")
    if outcome.result.status is not PlanStatus.SUCCEEDED:
        raise BenchError(f"the demo plan {outcome.result.status} at {outcome.result.stage}: {outcome.result.reason}")
    progress(f"demo plan succeeded in {seconds} s")
    return {"status": str(outcome.result.status), "seconds": seconds}


def measure(args: argparse.Namespace, progress: Progress) -> dict[str, Any]:
    services = stack_services("sim")
    settings = bench_settings("memory")
    result: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="bench-memory-") as tmp:
        config = {
            "sim": {"realtime_factor": args.sim_speed},
            "recorder": {"output_dir": str(Path(tmp) / "recordings")},
            "safety": {
                "operator_token_file": str(Path(tmp) / "operator-token"),
                "estop_state_file": str(Path(tmp) / "estop-state.json"),
            },
        }
        progress(f"starting {', '.join(services)} (robot {settings.robot}, base port {settings.base_port})")
        with running_stack(services, settings, Path(tmp), progress, config=config) as stack:
            node = stack.node
            # Alive is not yet reporting: a plan before the robot's first odometry is vetoed (unknown pose).
            Latest(node, keys.ODOM).wait(lambda _: True, READY_TIMEOUT, "odometry from the sim")
            started = read_processes(node, services)
            floors = [baseline(settings, services)["rss_bytes"] for _ in range(args.baseline_runs)]
            result["demo"] = run_demo(node, progress)
            samples: list[dict[str, ProcessStatus]] = []
            for i in range(args.samples):
                if i:
                    time.sleep(args.interval)
                samples.append(read_processes(node, services))
            shares = {name: proportional(stack.supervisor.procs[name].pid) for name in services}
            kids = {name: children(stack.supervisor.procs[name].pid) for name in services}
    floor = statistics.median(floors)
    each = {}
    for name in services:
        rss = statistics.median(sample[name].rss_bytes for sample in samples)
        share = shares[name]
        each[name] = {
            "rss_mb": mb(rss),
            "peak_rss_mb": mb(max(sample[name].peak_rss_bytes for sample in samples)),
            "rss_mb_after_start": mb(started[name].rss_bytes),
            "above_baseline_mb": mb(rss - floor),
            "pss_mb": mb(share) if share is not None else None,
            "cpu_seconds": round(samples[-1][name].cpu_seconds, 2),
        }
    helpers = {f"{name}/{child}": figures for name in services for child, figures in kids[name].items()}
    total = sum(statistics.median(sample[name].rss_bytes for sample in samples) for name in services)
    total += sum(rss for rss, _ in helpers.values())
    known = [share for share in shares.values() if share is not None]
    known += [share for _, share in helpers.values() if share is not None]
    result |= {
        "services": each,
        # Processes the services started (the sim's renderer), counted in the totals.
        "children": {
            name: {"rss_mb": mb(rss), "pss_mb": mb(share) if share is not None else None}
            for name, (rss, share) in helpers.items()
        },
        "total_rss_mb": mb(total),
        "total_rss_mb_after_start": mb(sum(p.rss_bytes for p in started.values())),
        "total_peak_rss_mb": mb(sum(max(s[name].peak_rss_bytes for s in samples) for name in services)),
        "total_pss_mb": mb(sum(known)) if len(known) == len(shares) + len(helpers) else None,
        "baseline_rss_mb": mb(floor),
        "baseline_runs_mb": [mb(f) for f in floors],
        "baseline_total_mb": mb(floor * len(services)),
        "goal_met": total / MB <= GOAL_TOTAL_MB,
    }
    progress(f"total {mb(total)} MB resident after the demo; the bare floor {mb(floor)} MB a process")
    return result


def run(args: argparse.Namespace) -> dict[str, Any]:
    progress = reporter(PROG)
    defaults = {
        "goal_total_rss_mb": GOAL_TOTAL_MB,
        "services": {},
        "total_rss_mb": None,
        "notes": notes(sim_speed=args.sim_speed, samples=args.samples, interval_s=args.interval),
    }
    return measured(defaults, lambda: measure(args, progress), progress)


def print_table(result: dict[str, Any]) -> None:
    rows = [(name, show(s["rss_mb"], " MB"), "") for name, s in result["services"].items()]
    rows += [
        ("total", show(result["total_rss_mb"], " MB"), f"<= {GOAL_TOTAL_MB:g} MB"),
        ("baseline per process", show(result.get("baseline_rss_mb"), " MB"), ""),
    ]
    print_rows("whole-stack memory after the demo", rows, result["errors"])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--sim-speed", type=bounded(float, 0.1, 20.0), default=4.0, help="simulated seconds per wall second"
    )
    parser.add_argument("--samples", type=bounded(int, 1, 100), default=5, help="readings after the demo")
    parser.add_argument(
        "--interval", type=bounded(float, 0.0, 10.0), default=0.2, help="seconds between readings after the demo"
    )
    parser.add_argument(
        "--baseline-runs", type=bounded(int, 1, 20), default=3, help="bare Zenoh processes measured for the floor"
    )


def main(argv: list[str] | None = None) -> None:
    bench_main(PROG, __doc__ or "", add_arguments, run, print_table, argv)


if __name__ == "__main__":
    main()
