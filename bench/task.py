"""Household tasks end to end: plans through every service, each judged by the simulator's ground truth.

`python -m bench.task --json` starts every service (the sim `--sim-speed` times faster than real
time), sends the tasks below one after the other (each starts where the last left the world:
fetch, tidy, deliver to the operator, in JSON, English and tool-call shapes), and judges each by
`sim/ground_truth` (never by what the executor reports): `tasks`, `succeeded`, `success_rate`,
`median_task_s` and `p99_task_s` (sim seconds per task). The baseline, measured in the same run on
the same tasks, is the time the base needs at its speed limit for the distance it actually drove
(`median_drive_bound_s`, from odometry): what is left over is turning, stopping, planning and the
arm. Goal: every task succeeds.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import tempfile
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench.service import (
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
from bench.transport import percentile
from schemas import keys
from schemas.executor import ExecutePlanGoal, PlanStatus
from schemas.robot import Odometry
from schemas.world import Empty, GroundTruth
from services.errors import CallError
from services.runtime import SERVICES, Node
from services.worldmodel import WorldModel, load_world
from tether.client import PlanSender

PROG = "bench.task"
# A delivered object counts as handed over within this of the person (metres, base centre).
HANDOVER_DISTANCE = 1.5
DOCKED = 0.1  # metres from the dock's pose


def on(object_id: str, surface: str) -> Callable[[GroundTruth], str | None]:
    def judge(truth: GroundTruth) -> str | None:
        obj = next(o for o in truth.objects if o.id == object_id)
        return None if obj.on == surface else f"{object_id} is on {obj.on or 'the floor'}, not on {surface}"

    return judge


def every(*judges: Callable[[GroundTruth], str | None]) -> Callable[[GroundTruth], str | None]:
    def judge(truth: GroundTruth) -> str | None:
        return next((why for j in judges if (why := j(truth)) is not None), None)

    return judge


def handed(object_id: str, person: tuple[float, float]) -> Callable[[GroundTruth], str | None]:
    def judge(truth: GroundTruth) -> str | None:
        if truth.holding != object_id:
            return f"the gripper holds {truth.holding or 'nothing'}, not {object_id}"
        away = math.dist((truth.robot.x, truth.robot.y), person)
        return None if away <= HANDOVER_DISTANCE else f"the robot stopped {away:.2f} m from the person"

    return judge


def at(x: float, y: float) -> Callable[[GroundTruth], str | None]:
    def judge(truth: GroundTruth) -> str | None:
        away = math.dist((truth.robot.x, truth.robot.y), (x, y))
        return None if away <= DOCKED else f"the robot stands {away:.2f} m from ({x}, {y})"

    return judge


@dataclass(frozen=True)
class Task:
    name: str
    plan: str
    judge: Callable[[GroundTruth], str | None]


def plan(*steps: dict[str, Any], description: str = "") -> str:
    return json.dumps({"plan": list(steps), "description": description})


def tasks() -> list[Task]:
    """The suite, in order: each task starts in the world the previous one left."""
    world = WorldModel(load_world())
    operator = world.world.humans[0].pose
    dock = next(p.pose for p in world.world.places if p.id == "charging_dock")
    me = (operator.x, operator.y)
    return [
        Task(
            "fetch the red cup to the coffee table",
            plan(
                {"action": "navigate_to", "target": "kitchen counter"},
                {"action": "pick", "target": "red cup"},
                {"action": "navigate_to", "target": "coffee table"},
                {"action": "place", "target": "coffee table"},
            ),
            on("red_cup", "coffee_table"),
        ),
        Task(
            "tidy the book onto the shelf",
            plan({"action": "pick", "target": "blue book"}, {"action": "place", "target": "shelf"}),
            on("blue_book", "shelf"),
        ),
        Task(
            "tidy the apple onto the counter (English)",
            "1. Go to the kitchen table\n2. Pick up the apple\n3. Put it on the kitchen counter\n",
            on("apple", "kitchen_counter"),
        ),
        Task(
            "deliver the coffee mug to the operator",
            plan(
                {"action": "pick", "target": "coffee mug"},
                {"action": "navigate_to", "target": "me"},
                {"action": "say", "target": "here is your coffee mug"},
            ),
            handed("coffee_mug", me),
        ),
        Task(
            "put the mug down on the coffee table",
            plan({"action": "place", "target": "coffee table"}),
            on("coffee_mug", "coffee_table"),
        ),
        Task(
            "the blue cup onto the chair (tool call)",
            json.dumps(
                {
                    "tool_calls": [
                        {
                            "type": "function",
                            "function": {"name": "pick", "arguments": json.dumps({"target": "blue cup"})},
                        },
                        {
                            "type": "function",
                            "function": {"name": "place", "arguments": json.dumps({"target": "chair"})},
                        },
                    ]
                }
            ),
            on("blue_cup", "chair"),
        ),
        Task(
            "the red cup onto the bed",
            plan({"action": "pick", "target": "red cup"}, {"action": "place", "target": "bed"}),
            on("red_cup", "bed"),
        ),
        Task(
            "fetch the book from the shelf to the kitchen table",
            plan({"action": "pick", "target": "blue book"}, {"action": "place", "target": "kitchen table"}),
            on("blue_book", "kitchen_table"),
        ),
        Task(
            "tidy two things: the apple to the kitchen table, the blue cup to the counter",
            plan(
                {"action": "pick", "target": "apple"},
                {"action": "place", "target": "kitchen table"},
                {"action": "pick", "target": "blue cup"},
                {"action": "place", "target": "kitchen counter"},
            ),
            every(on("apple", "kitchen_table"), on("blue_cup", "kitchen_counter")),
        ),
        Task(
            "bring the red cup back to the counter",
            plan({"action": "pick", "target": "red cup"}, {"action": "place", "target": "kitchen counter"}),
            on("red_cup", "kitchen_counter"),
        ),
        Task(
            "look round every room, then dock",
            plan(
                *({"action": "navigate_to", "target": room} for room in ("office", "bedroom", "kitchen", "hallway")),
                {"action": "navigate_to", "target": "charging dock"},
            ),
            at(dock.x, dock.y),
        ),
    ]


class Odometer:
    """The distance the base drives, summed from robot/odom."""

    def __init__(self, node: Node) -> None:
        self._lock = threading.Lock()
        self._last: tuple[float, float] | None = None
        self.metres = 0.0
        node.subscribe(keys.ODOM, self._on_odom)

    def _on_odom(self, odom: Odometry) -> None:
        with self._lock:
            here = (odom.pose.x, odom.pose.y)
            if self._last is not None:
                self.metres += math.dist(self._last, here)
            self._last = here

    def read(self) -> float:
        with self._lock:
            return self.metres


def truth(node: Node) -> GroundTruth:
    reply: GroundTruth = node.call(keys.GROUND_TRUTH, Empty(), timeout=5.0)
    return reply


def run_tasks(node: Node, suite: list[Task], timeout: float, progress: Progress) -> dict[str, Any]:
    sender = PlanSender(node)
    odometer = Odometer(node)
    results: list[dict[str, Any]] = []
    for k, task in enumerate(suite, start=1):
        before, driven = truth(node), odometer.read()
        progress(f"task {k}/{len(suite)}: {task.name}")
        try:
            run = sender.run(ExecutePlanGoal(text=task.plan), timeout)
            status = run.result.status if run.result else PlanStatus.FAILED
            reason = run.result.reason if run.result else "no result"
        except CallError as exc:
            status, reason = PlanStatus.FAILED, f"no result: {exc}"
        after = truth(node)
        verdict = task.judge(after)
        ok = status is PlanStatus.SUCCEEDED and verdict is None
        seconds = after.sim_time - before.sim_time
        metres = odometer.read() - driven
        results.append(
            {
                "task": task.name,
                "succeeded": ok,
                "status": str(status),
                "sim_s": round(seconds, 2),
                "driven_m": round(metres, 2),
                "why": "" if ok else (reason if status is not PlanStatus.SUCCEEDED else verdict),
            }
        )
        progress(f"  {'ok' if ok else 'FAILED'} in {seconds:.1f} sim s" + ("" if ok else f": {results[-1]['why']}"))
    times = [r["sim_s"] for r in results]
    max_speed = load_world().robot.max_linear_speed
    bounds = [r["driven_m"] / max_speed for r in results]
    succeeded = sum(r["succeeded"] for r in results)
    return {
        "tasks": len(results),
        "succeeded": succeeded,
        "success_rate": round(succeeded / len(results), 4),
        "median_task_s": round(statistics.median(times), 2),
        "p99_task_s": round(percentile(times, 99), 2),
        "median_drive_bound_s": round(statistics.median(bounds), 2),
        "per_task": results,
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    progress = reporter(PROG)
    suite = tasks()[: args.tasks]
    defaults: dict[str, Any] = {
        "tasks": len(suite),
        "succeeded": 0,
        "success_rate": 0.0,
        "median_task_s": None,
        "p99_task_s": None,
        "median_drive_bound_s": None,
        "goal_success_rate": 1.0,
        **notes(sim_speed=args.sim_speed),
    }

    def measure() -> dict[str, Any]:
        settings = bench_settings("task")
        with tempfile.TemporaryDirectory(prefix="bench-task-") as tmp:
            config = {
                "sim": {"realtime_factor": args.sim_speed},
                "recorder": {"output_dir": str(Path(tmp) / "recordings")},
                "safety": {"operator_token_file": str(Path(tmp) / "operator-token")},
            }
            progress(f"starting every service (robot {settings.robot}, sim at {args.sim_speed:g}x)")
            with running_stack(SERVICES, settings, Path(tmp), progress, config=config) as stack:
                return run_tasks(stack.node, suite, args.timeout, progress)

    return measured(defaults, measure, progress)


def print_table(result: dict[str, Any]) -> None:
    rows = [
        (r["task"], "ok" if r["succeeded"] else f"FAILED: {r['why']}", f"{r['sim_s']} s")
        for r in result.get("per_task", [])
    ]
    rows += [
        ("success rate", show(result["success_rate"]), show(result["goal_success_rate"])),
        ("median task (sim s)", show(result["median_task_s"]), ""),
        ("median drive bound (sim s)", show(result["median_drive_bound_s"]), "baseline"),
    ]
    print_rows("bench.task: household tasks judged by ground truth", rows, result["errors"])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--sim-speed", type=bounded(float, 1.0, 20.0), default=10.0, help="sim seconds per wall second (default 10)"
    )
    parser.add_argument(
        "--timeout", type=bounded(float, 10.0, 3600.0), default=900.0, help="wall seconds allowed per task"
    )
    parser.add_argument(
        "--tasks", type=bounded(int, 1, 100), default=100, help="run only the first N tasks of the suite (in order)"
    )


def main(argv: list[str] | None = None) -> None:
    bench_main(PROG, __doc__ or PROG, add_arguments, run, print_table, argv)


if __name__ == "__main__":
    main()
