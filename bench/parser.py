"""Parser throughput in-process, and plan/parse round trips to the real parser service against bare Zenoh.

    python -m bench.parser --json        one JSON object on stdout, progress on stderr
    python -m bench.parser               a short table

Throughput: a 10-step JSON plan and a 10-line English plan through `services.parser.parser.parse`,
each timed alone; plans/s is one over the median parse time. Either plan parsed into other than
its 10 steps is an error, in-process and in the round trips alike: such a parse is not this work.

Round trips: the parser service is a real process started by the Supervisor on its own robot name
and ports; readiness is its liveliness token. The baseline is the bare Zenoh echo of
`bench.transport`, answered by the same parser process on the same session (see `bench.service`).
Both kinds of round trip are interleaved, alternating which goes first, as in `bench.transport`.

A plan/parse round trip is all a client pays for a parse: `Node.call` encodes the PlanText, the
service (served inline, on Zenoh's callback thread) decodes it, parses the plan (a real parse each
time, nothing cached), encodes the Plan and replies; the client decodes the Plan. The service's
log line and its trace on `_trace/**` follow the reply on the same thread, so they are not in the
round trip, but they are in the service's time: a query that comes before they are done waits for
them (the next echo or parse, whichever comes next). The echo replies with the request's bytes,
undecoded.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.service import BenchError, against_echo, bench_settings, command_line, ms_summary, running_service
from bench.transport import machine
from schemas import keys
from schemas.plan import Plan, PlanText
from services import runtime
from services.errors import CallError
from services.runtime import Node

SERVICE = "parser"
STEPS = 10  # in each plan below
GOALS = {"goal_json_plans_per_s": 5000.0, "goal_text_plans_per_s": 1000.0, "goal_ratio_p50": 1.5}
CALL_TIMEOUT = 2.0

JSON_PLAN = json.dumps(
    {
        "description": "Bring the red cup from the kitchen to the living room",
        "plan": [
            {"action": "navigate_to", "target": "kitchen", "description": "go where the cup is"},
            {"action": "pick_up", "target_object": "red cup", "target_location": "kitchen counter"},
            {"action": "navigate_to", "target": "living room", "parameters": {"speed": 0.5}},
            {"action": "place", "target_object": "red cup", "target_location": "coffee table"},
            {"action": "say", "parameters": {"text": "here you are"}},
            {"action": "turn", "parameters": {"angle": "90 degrees", "direction": "left"}},
            {"action": "drive", "parameters": {"distance": "30 cm", "direction": "forward"}},
            {"action": "wait", "parameters": {"duration": 2}},
            {"action": "open_gripper"},
            {"action": "navigate_to", "target": "kitchen", "description": "go back"},
        ],
    },
    indent=2,
)
TEXT_PLAN = (
    "1. Go to the kitchen\n"
    "2. Pick up the red cup from the kitchen counter\n"
    "3. Go to the living room\n"
    "4. Put it on the coffee table\n"
    '5. Say "here you are"\n'
    "6. Turn left 90 degrees\n"
    "7. Drive forward 30 cm\n"
    "8. Wait 2 seconds\n"
    "9. Open the gripper\n"
    "10. Go back to the kitchen"
)
REQUEST = PlanText(text=JSON_PLAN, format="json")


def progress(message: str) -> None:
    print(f"bench.parser: {message}", file=sys.stderr, flush=True)


# In-process throughput


def parse_times(text: str, fmt: str, seconds: float, warmup: int) -> list[float]:
    """Milliseconds per parse, each timed alone, for `seconds` after `warmup` uncounted parses."""
    try:
        # Imported here, so a parser that does not even import is reported like one that fails.
        from services.parser.parser import parse

        plan = parse(text, fmt)
    except Exception as exc:  # a bench reports any failure of the code it measures, then goes on
        raise BenchError(f"{fmt} plan: {type(exc).__name__}: {exc}") from None
    # A parse that drops steps does less work: its time would not be this plan's.
    if len(plan.steps) != STEPS:
        raise BenchError(f"the {fmt} plan parsed into {len(plan.steps)} steps, not {STEPS}")
    for _ in range(warmup):
        parse(text, fmt)
    times: list[float] = []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline or len(times) < 10:
        started = time.perf_counter_ns()
        parse(text, fmt)
        times.append((time.perf_counter_ns() - started) / 1e6)
    return times


def throughput(text: str, fmt: str, seconds: float, warmup: int) -> dict[str, Any]:
    progress(f"parsing the {fmt} plan in-process for {seconds:g} s")
    times = parse_times(text, fmt, seconds, warmup)
    p50, p99 = ms_summary(times)
    return {"plans_per_s": round(1000.0 / p50, 1), "p50_ms": p50, "p99_ms": p99, "n": len(times)}


# Round trips to the service


def round_trips(node: Node, n: int, warmup: int, max_seconds: float) -> tuple[list[float], list[float]]:
    """Interleaved round trips in ms: (bare echo, plan/parse), the echo carrying the parse request's bytes."""

    def query() -> None:
        try:
            plan = node.call(keys.PLAN_PARSE, REQUEST, timeout=CALL_TIMEOUT)
        except CallError as exc:
            raise BenchError(f"plan/parse refused the JSON plan: {exc.error.message}") from None
        if not isinstance(plan, Plan):
            raise BenchError(f"plan/parse replied with {type(plan).__name__}, not a Plan")
        if len(plan.steps) != STEPS:
            raise BenchError(f"plan/parse parsed the JSON plan into {len(plan.steps)} steps, not {STEPS}")

    return against_echo(node, SERVICE, runtime.encode(REQUEST), query, n, warmup, max_seconds)


def service_latency(n: int, warmup: int, max_seconds: float) -> dict[str, Any]:
    settings = bench_settings(SERVICE)
    with tempfile.TemporaryDirectory(prefix="bench-parser-") as tmp:
        progress(f"starting the parser service (robot {settings.robot}, base port {settings.base_port})")
        with running_service(SERVICE, settings, Path(tmp), progress) as node:
            progress(f"measuring up to {n} round trips of each kind (+{warmup} warm-up, at most {max_seconds:g} s)")
            bare, queries = round_trips(node, n, warmup, max_seconds)
    q50, q99 = ms_summary(queries)
    b50, b99 = ms_summary(bare)
    return {
        "query_p50_ms": q50,
        "query_p99_ms": q99,
        "bare_p50_ms": b50,
        "bare_p99_ms": b99,
        "ratio_p50": round(q50 / b50, 3),
        "ratio_p99": round(q99 / b99, 3),
        "n": len(queries),
    }


# The whole bench


def run(seconds: float, n: int, warmup: int, max_query_seconds: float) -> dict[str, Any]:
    result: dict[str, Any] = {
        "json_plans_per_s": None,
        "text_plans_per_s": None,
        "query_p50_ms": None,
        "query_p99_ms": None,
        "bare_p50_ms": None,
        "bare_p99_ms": None,
        "ratio_p50": None,
        "ratio_p99": None,
        "n": 0,
        "warmup": warmup,
        **GOALS,
    }
    errors: list[str] = []
    parse_detail: dict[str, Any] = {}
    for fmt, text in (("json", JSON_PLAN), ("text", TEXT_PLAN)):
        try:
            measured = throughput(text, fmt, seconds, warmup)
        except BenchError as exc:
            errors.append(str(exc))
            progress(f"error: {exc}")
            continue
        result[f"{fmt}_plans_per_s"] = measured.pop("plans_per_s")
        parse_detail[fmt] = measured
    try:
        result |= service_latency(n, warmup, max_query_seconds)
    except BenchError as exc:
        errors.append(str(exc))
        progress(f"error: {exc}")
    result["goals_met"] = {
        "json_plans_per_s": _at_least(result["json_plans_per_s"], GOALS["goal_json_plans_per_s"]),
        "text_plans_per_s": _at_least(result["text_plans_per_s"], GOALS["goal_text_plans_per_s"]),
        "ratio_p50": None if result["ratio_p50"] is None else result["ratio_p50"] <= GOALS["goal_ratio_p50"],
    }
    result["errors"] = errors
    result["notes"] = {
        **machine(),
        "parse_seconds_per_format": seconds,
        "parse": parse_detail,
        "plans_per_s": "1000 / median ms of a single parse, each parse timed alone, after warm-up",
        "query": "plan/parse with the 10-step JSON plan (format json) to a parser process started by the Supervisor: "
        "encode, decode, parse, encode, reply, decode the Plan; the log line and trace follow the reply",
        "bare": "bare Zenoh get on bench/raw_echo/parser, echoed by the same parser process and session, "
        "same request bytes",
        "order": "interleaved, alternating first call",
        "request_bytes": len(runtime.encode(REQUEST)),
        "service_log_level": os.environ.get("TETHER_LOG_LEVEL", "INFO"),
    }
    return result


def _at_least(value: float | None, goal: float) -> bool | None:
    return None if value is None else value >= goal


def print_table(result: dict[str, Any]) -> None:
    from rich.console import Console
    from rich.table import Table

    def show(value: Any, unit: str = "") -> str:
        return "-" if value is None else f"{value:,.3f}{unit}" if isinstance(value, float) else f"{value}{unit}"

    table = Table(title=f"parser ({result['n']} round trips, {result['warmup']} warm-up)")
    table.add_column("")
    table.add_column("measured", justify="right")
    table.add_column("goal", justify="right")
    table.add_row("JSON plans/s", show(result["json_plans_per_s"]), show(GOALS["goal_json_plans_per_s"]))
    table.add_row("text plans/s", show(result["text_plans_per_s"]), show(GOALS["goal_text_plans_per_s"]))
    table.add_row("plan/parse p50 / p99 ms", f"{show(result['query_p50_ms'])} / {show(result['query_p99_ms'])}", "")
    table.add_row("bare zenoh p50 / p99 ms", f"{show(result['bare_p50_ms'])} / {show(result['bare_p99_ms'])}", "")
    table.add_row("ratio p50", show(result["ratio_p50"], "x"), show(GOALS["goal_ratio_p50"], "x"))
    console = Console()
    console.print(table)
    for error in result["errors"]:
        console.print(f"[red]error:[/] {error}", markup=True, highlight=False)


def main(argv: list[str] | None = None) -> None:
    command_line(
        "bench.parser",
        __doc__ or "",
        run,
        print_table,
        argv,
        seconds=5.0,
        seconds_help="in-process parsing time per format",
    )


if __name__ == "__main__":
    main()
