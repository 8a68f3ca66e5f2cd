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
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench.service import (
    BenchError,
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
from schemas.world import Empty, GroundTruth, Moved, MoveEntity
from services.errors import CallError
from services.runtime import SERVICES, Node
from services.worldmodel import WorldModel, load_world
from tether.client import PlanSender

PROG = "bench.task"
# A delivered object counts as handed over within this of the person (metres, base centre).
HANDOVER_DISTANCE = 1.5
# A delivery put down counts within this of the person (metres, object to person).
DELIVERY_DISTANCE = 2.5
DOCKED = 0.1  # metres from the dock's pose


Judge = Callable[[GroundTruth], str | None]


def on(object_id: str, surface: str) -> Judge:
    def judge(truth: GroundTruth) -> str | None:
        obj = next(o for o in truth.objects if o.id == object_id)
        return None if obj.on == surface else f"{object_id} is on {obj.on or 'the floor'}, not on {surface}"

    return judge


def every(*judges: Judge) -> Judge:
    def judge(truth: GroundTruth) -> str | None:
        return next((why for j in judges if (why := j(truth)) is not None), None)

    return judge


def handed(object_id: str, person: tuple[float, float]) -> Judge:
    def judge(truth: GroundTruth) -> str | None:
        if truth.holding != object_id:
            return f"the gripper holds {truth.holding or 'nothing'}, not {object_id}"
        away = math.dist((truth.robot.x, truth.robot.y), person)
        return None if away <= HANDOVER_DISTANCE else f"the robot stopped {away:.2f} m from the person"

    return judge


def delivered(object_id: str, person: tuple[float, float], world: WorldModel) -> Judge:
    """Put down for the person: released, on a furniture top within DELIVERY_DISTANCE of them (never
    on the floor at their feet, never still in the hand)."""

    def judge(truth: GroundTruth) -> str | None:
        obj = next(o for o in truth.objects if o.id == object_id)
        item = world.furniture.get(obj.on or "")
        if item is None:
            return f"{object_id} is {'in the gripper' if obj.on == 'gripper' else 'on ' + (obj.on or 'the floor')}"
        away = math.dist((obj.position.x, obj.position.y), person)
        return None if away <= DELIVERY_DISTANCE else f"{object_id} is on the {item.name}, {away:.2f} m from the person"

    return judge


def at(x: float, y: float) -> Judge:
    def judge(truth: GroundTruth) -> str | None:
        away = math.dist((truth.robot.x, truth.robot.y), (x, y))
        return None if away <= DOCKED else f"the robot stands {away:.2f} m from ({x}, {y})"

    return judge


@dataclass(frozen=True)
class Task:
    """A plan as some model would write it, judged by ground truth. `setup` moves things in the sim
    first (behind the robot's back: perception and memory learn of it only by looking)."""

    name: str
    plan: str
    judge: Judge
    setup: tuple[MoveEntity, ...] = ()


def plan(*steps: dict[str, Any], description: str = "") -> str:
    return json.dumps({"plan": list(steps), "description": description})


# Tool calls as each vendor's API returns them: (tool name, arguments).
Call = tuple[str, dict[str, Any]]


def openai_chat(*calls: Call) -> str:
    """A chat.completions response whose message calls tools."""
    tool_calls = [
        {"id": f"call_{k}", "type": "function", "function": {"name": name, "arguments": json.dumps(args)}}
        for k, (name, args) in enumerate(calls)
    ]
    message = {"role": "assistant", "content": None, "tool_calls": tool_calls}
    choice = {"index": 0, "message": message, "finish_reason": "tool_calls"}
    return json.dumps({"id": "chatcmpl-1", "object": "chat.completion", "choices": [choice]})


def openai_responses(*calls: Call) -> str:
    """A Responses API response: a reasoning item, then one function_call item per call."""
    output: list[dict[str, Any]] = [{"type": "reasoning", "id": "rs_1", "summary": []}]
    output += [
        {"type": "function_call", "id": f"fc_{k}", "call_id": f"call_{k}", "name": name,
         "arguments": json.dumps(args), "status": "completed"}
        for k, (name, args) in enumerate(calls)
    ]  # fmt: skip
    return json.dumps({"id": "resp_1", "object": "response", "status": "completed", "output": output})


def anthropic(*calls: Call, text: str = "") -> str:
    """A Messages API response with tool_use blocks (after a text block, as Claude writes them)."""
    content: list[dict[str, Any]] = [{"type": "text", "text": text}] if text else []
    content += [
        {"type": "tool_use", "id": f"toolu_{k}", "name": name, "input": args} for k, (name, args) in enumerate(calls)
    ]
    return json.dumps({"id": "msg_1", "type": "message", "role": "assistant", "content": content,
                       "stop_reason": "tool_use"})  # fmt: skip


def gemini(*calls: Call) -> str:
    """A generateContent response whose candidate's parts are functionCall parts."""
    parts = [{"functionCall": {"name": name, "args": args}} for name, args in calls]
    return json.dumps({"candidates": [{"content": {"role": "model", "parts": parts}, "finishReason": "STOP"}]})


def mcp(*calls: Call) -> str:
    """A JSON-RPC batch of MCP tools/call requests."""
    return json.dumps(
        [
            {"jsonrpc": "2.0", "id": k, "method": "tools/call", "params": {"name": name, "arguments": args}}
            for k, (name, args) in enumerate(calls)
        ]
    )


def moved(object_id: str, x: float, y: float) -> MoveEntity:
    return MoveEntity(id=object_id, x=x, y=y)


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
            "deliver the coffee mug to the operator, held out",
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
            "the blue cup onto the chair (legacy tool_calls)",
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
        # World now: red cup, blue cup on the counter; mug on the coffee table; apple, book on the
        # kitchen table; the robot at the dock.
        Task("bring me the apple (English)", "Bring me the apple.", delivered("apple", me, world)),
        Task(
            "the book onto the shelf (OpenAI Responses)",
            openai_responses(("pick", {"target": "blue book"}), ("place", {"target": "shelf"})),
            on("blue_book", "shelf"),
        ),
        Task(
            "the red cup onto the kitchen table (Gemini)",
            gemini(("pick", {"object": "red cup"}), ("place", {"surface": "kitchen table"})),
            on("red_cup", "kitchen_table"),
        ),
        Task(
            "the mug onto the counter (Anthropic tool_use)",
            anthropic(
                ("navigate_to", {"target": "coffee table"}),
                ("pick", {"target": "coffee mug"}),
                ("place", {"target": "kitchen counter"}),
                text="I'll take the mug back to the kitchen.",
            ),
            on("coffee_mug", "kitchen_counter"),
        ),
        Task(
            "the apple onto the kitchen table (MCP tools/call)",
            mcp(("pick", {"target": "apple"}), ("place", {"target": "kitchen table"})),
            on("apple", "kitchen_table"),
        ),
        Task(
            "the blue cup onto the bed (YAML)",
            "```yaml\nplan:\n  - action: pick\n    target: blue cup\n  - action: place\n    target: bed\n```\n",
            on("blue_cup", "bed"),
        ),
        Task(
            "the blue cup back to the kitchen table (array of sentences)",
            json.dumps(["Go to the bedroom", "Pick up the blue cup", "Put it on the kitchen table"]),
            on("blue_cup", "kitchen_table"),
        ),
        Task(
            "the apple onto the counter (prose)",
            "Sure. Please go to the kitchen table, pick up the apple and then put it on the kitchen counter.",
            on("apple", "kitchen_counter"),
        ),
        Task(
            "the red cup onto the coffee table, with grasp hints (OpenAI chat)",
            openai_chat(
                ("pick", {"target": "red cup", "approach": "pinch", "grasp_type": "precision"}),
                ("place", {"target": "coffee table", "approach_distance": "10 cm"}),
            ),
            on("red_cup", "coffee_table"),
        ),
        Task(
            "carry the red cup carefully to the shelf (English, manner words)",
            "1. Pick up the red cup carefully\n2. Put it on the shelf gently\n",
            on("red_cup", "shelf"),
        ),
        Task(
            "the book moved since last seen: from the bed to the coffee table",
            plan({"action": "pick", "target": "blue book"}, {"action": "place", "target": "coffee table"}),
            on("blue_book", "coffee_table"),
            setup=(moved("blue_book", 2.0, 7.2),),  # from the shelf onto the bed (its near edge), unseen
        ),
        Task(
            "go to the kitchen, detect the mug, grasp it (mug out of view, moved along the counter)",
            plan(
                {"action": "navigate_to", "target": "kitchen"},
                {"action": "detect", "target": "coffee mug"},
                {"action": "pick", "target": "coffee mug"},
                {"action": "place", "target": "kitchen table"},
            ),
            on("coffee_mug", "kitchen_table"),
            setup=(moved("coffee_mug", 1.7, 0.35),),
        ),
        Task(
            "pick up the red cup and put it back",
            "1. Pick up the red cup\n2. Put it back\n",
            every(on("red_cup", "shelf"), lambda t: None if t.holding is None else f"still holding {t.holding}"),
        ),
        Task("go home (English)", "Go home.", at(dock.x, dock.y)),
        Task(
            "fetch the coffee mug (JSON verb, to the person who asked)",
            json.dumps({"plan": [{"action": "fetch", "target": "coffee mug"}]}),
            delivered("coffee_mug", me, world),
        ),
        Task(
            "bring the red cup to the operator (English)",
            "Bring the red cup to the operator",
            delivered("red_cup", me, world),
        ),
        Task(
            "tidy up the cups onto the kitchen counter (multi-object, English list)",
            "- tidy up the red cup onto the kitchen counter\n- tidy up the blue cup onto the kitchen counter\n"
            "- tidy up the coffee mug onto the kitchen counter\n",
            every(
                on("red_cup", "kitchen_counter"), on("blue_cup", "kitchen_counter"), on("coffee_mug", "kitchen_counter")
            ),
        ),
        Task(
            "with a fallback: the apple to the shelf, else to the kitchen table",
            plan(
                {"action": "pick", "target": "apple"},
                {"action": "place", "target": "shelf", "on_failure": [{"action": "place", "target": "kitchen table"}]},
            ),
            lambda t: (
                None
                if next(o for o in t.objects if o.id == "apple").on in ("shelf", "kitchen_table")
                else "the apple is on neither the shelf nor the kitchen table"
            ),
        ),
        Task(
            "other field names: skill/object/surface under steps",
            json.dumps(
                {
                    "steps": [
                        {"skill": "pick_up", "object": "blue book"},
                        {"skill": "put_down", "surface": "kitchen table"},
                    ]
                }
            ),
            on("blue_book", "kitchen_table"),
        ),
        Task(
            "a plan in a fenced block inside prose (the apple to the coffee table)",
            "Here is the plan:\n\n```json\n"
            + json.dumps(
                {"plan": [{"action": "pick", "target": "apple"}, {"action": "place", "target": "coffee table"}]}
            )
            + "\n```\nLet me know if anything fails.",
            on("apple", "coffee_table"),
        ),
        Task(
            "an execute_plan tool call carrying a whole plan, then return to the dock (OpenAI chat)",
            openai_chat(
                (
                    "execute_plan",
                    {
                        "plan": [
                            {"action": "pick", "target": "apple"},
                            {"action": "place", "target": "kitchen table"},
                            {"action": "navigate_to", "target": "charging dock"},
                        ]
                    },
                ),
            ),
            every(on("apple", "kitchen_table"), at(dock.x, dock.y)),
        ),
        Task("return to the dock (English, already nearly there)", "Return to the dock", at(dock.x, dock.y)),
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
        for move in task.setup:
            moved = node.call(keys.SIM_MOVE, move, timeout=10.0)
            if not isinstance(moved, Moved):
                raise BenchError(f"task {k}: the sim did not move {move.id}: {moved}")
        before, driven, started = truth(node), odometer.read(), time.monotonic()
        progress(f"task {k}/{len(suite)}: {task.name}")
        searched: list[str] = []
        search_wall = 0.0
        try:
            run = sender.run(ExecutePlanGoal(text=task.plan), timeout)
            status = run.result.status if run.result else PlanStatus.FAILED
            reason = run.result.reason if run.result else "no result"
            for step in run.result.steps if run.result else []:
                searched += step.searched
                search_wall += step.search_s
        except CallError as exc:
            status, reason = PlanStatus.FAILED, f"no result: {exc}"
        after, wall = truth(node), time.monotonic() - started
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
                # The executor times its searches by the wall clock: in sim seconds at this task's pace.
                "search_s": round(search_wall * seconds / wall, 2) if wall > 0 else 0.0,
                "searched": searched,
                "driven_m": round(metres, 2),
                "why": "" if ok else (reason if status is not PlanStatus.SUCCEEDED else verdict),
            }
        )
        progress(f"  {'ok' if ok else 'FAILED'} in {seconds:.1f} sim s" + ("" if ok else f": {results[-1]['why']}"))
    times = [r["sim_s"] for r in results]
    max_speed = load_world().robot.max_linear_speed
    bounds = [r["driven_m"] / max_speed for r in results]
    succeeded = sum(r["succeeded"] for r in results)
    searches = [r["search_s"] for r in results if r["search_s"] > 0]
    return {
        "tasks": len(results),
        "succeeded": succeeded,
        "success_rate": round(succeeded / len(results), 4),
        "median_task_s": round(statistics.median(times), 2),
        "p99_task_s": round(percentile(times, 99), 2),
        "tasks_with_search": len(searches),
        "search_s": round(sum(searches), 2),
        "median_search_s": round(statistics.median(searches), 2) if searches else 0.0,
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
        "tasks_with_search": 0,
        "search_s": 0.0,
        "median_search_s": None,
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
        ("p99 task (sim s)", show(result["p99_task_s"]), ""),
        (f"searching, {result['tasks_with_search']} tasks (sim s)", show(result["search_s"]), ""),
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
