"""Resolver accuracy over the reference corpus, and plan/resolve round trips to the real resolver service.

    python -m bench.resolver --json        one JSON object on stdout, progress on stderr
    python -m bench.resolver               a short table

Accuracy: every case of tests/corpus/resolver/references.yaml through its runner, in-process, with a
Resolver built as the service builds it; `accuracy` is correct cases over all cases.

Round trips: the resolver service is a real process started by the Supervisor on its own robot name
and ports (see `bench.service`), with no sim: it grounds the 10-step household plan below in the
world file alone (no perception, no odometry; the plan has no relative move before an absolute one).
Each query is interleaved with the bare Zenoh echo carrying the same bytes, answered by the same
process. The resolver keeps successful resolutions for identical plans, so two kinds are measured:
`resolve_*` with a plan that differs in every query (its wait duration), which the cache never
answers, and `cached_*` with one plan repeated, which it answers after the first.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.service import BenchError, against_echo, bench_settings, command_line, ms_summary, running_service
from bench.transport import machine
from schemas import keys
from schemas.common import ServiceError
from schemas.plan import Action, GroundedPlan, Plan, Step
from services import runtime
from services.errors import CallError
from services.runtime import Node

SERVICE = "resolver"
CALL_TIMEOUT = 2.0
# Distinct wait durations, in ms, before one comes round again: more than any run's queries.
DISTINCT = 60_000
INCORRECT_SHOWN = 20


def bench_plan(wait: float = 1.0) -> Plan:
    """The 10-step household plan: every action the resolver grounds from the world file alone."""
    return Plan(
        description="Bring the red cup to the coffee table, then fetch the apple",
        steps=[
            Step(action=Action.NAVIGATE_TO, target="kitchen counter"),
            Step(action=Action.PICK, target="red cup", location="kitchen counter"),
            Step(action=Action.NAVIGATE_TO, target="living room", params={"speed": 0.5}, units={"speed": "m/s"}),
            Step(action=Action.PLACE, target="red cup", location="coffee table"),
            Step(action=Action.DETECT, target="blue book"),
            Step(action=Action.SAY, params={"text": "here is your cup"}),
            Step(action=Action.NAVIGATE_TO, target="kitchen table"),
            Step(action=Action.PICK, target="apple"),
            Step(action=Action.LOOK_AT, target="operator"),
            Step(action=Action.WAIT, params={"duration": wait}, units={"duration": "s"}),
        ],
    )


def progress(message: str) -> None:
    print(f"bench.resolver: {message}", file=sys.stderr, flush=True)


# Accuracy over the corpus, in-process


def accuracy() -> dict[str, Any]:
    try:
        # Imported here: the corpus lives with the tests, and a resolver mid-change is reported, not fatal.
        from tests.corpus.resolver.runner import default_resolver, load_cases, run_case

        resolver = default_resolver()
        cases = load_cases(resolver.world)
    except Exception as exc:  # a bench reports any failure of the code it measures, then goes on
        raise BenchError(f"corpus: {type(exc).__name__}: {exc}") from None
    progress(f"resolving {len(cases)} reference cases in-process")
    outcomes = [run_case(case, resolver) for case in cases]
    correct = sum(o.passed for o in outcomes)
    incorrect = [o.detail.splitlines()[0][:300] for o in outcomes if not o.passed]
    return {
        "references": len(cases),
        "correct": correct,
        "accuracy": round(correct / len(cases), 4) if cases else None,
        "incorrect": incorrect[:INCORRECT_SHOWN],
    }


def inprocess_ms(seconds: float, warmup: int) -> list[float]:
    """Milliseconds per resolve of the bench plan in this process, each timed alone."""
    try:
        from tests.corpus.resolver.runner import default_resolver

        resolver = default_resolver()
        plan = bench_plan()
        resolver.resolve(plan)
    except Exception as exc:
        raise BenchError(f"in-process resolve: {type(exc).__name__}: {exc}") from None
    for _ in range(warmup):
        resolver.resolve(plan)
    times: list[float] = []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline or len(times) < 10:
        started = time.perf_counter_ns()
        resolver.resolve(plan)
        times.append((time.perf_counter_ns() - started) / 1e6)
    return times


# Round trips to the service


def resolve(node: Node, plan: Plan) -> None:
    try:
        reply = node.call(keys.PLAN_RESOLVE, plan, timeout=CALL_TIMEOUT)
    except CallError as exc:
        raise BenchError(f"plan/resolve refused the bench plan: {exc.error.message}") from None
    if isinstance(reply, ServiceError) or not isinstance(reply, GroundedPlan):
        raise BenchError(f"plan/resolve replied with {type(reply).__name__}, not a GroundedPlan")


def service_latency(n: int, warmup: int, max_seconds: float) -> dict[str, Any]:
    settings = bench_settings(SERVICE)
    # The echo carries as many bytes as a plan/resolve query, so both move the same payload.
    repeated = bench_plan()
    payload = runtime.encode(repeated)
    counter = iter(range(1, 1 << 62))
    with tempfile.TemporaryDirectory(prefix="bench-resolver-") as tmp:
        progress(f"starting the resolver service (robot {settings.robot}, base port {settings.base_port})")
        with running_service(SERVICE, settings, Path(tmp), progress) as node:

            def distinct() -> None:
                resolve(node, bench_plan(wait=next(counter) % DISTINCT / 1000))

            def cached() -> None:
                resolve(node, repeated)

            resolve(node, repeated)  # the plan resolves, and the cache holds it from now on
            progress(f"measuring up to {n} distinct plans against the echo (+{warmup} warm-up, <= {max_seconds:g} s)")
            bare, queries = against_echo(node, SERVICE, payload, distinct, n, warmup, max_seconds)
            progress(f"measuring up to {n} repeats of one plan against the echo")
            cached_bare, repeats = against_echo(node, SERVICE, payload, cached, n, warmup, max_seconds)
    q50, q99 = ms_summary(queries)
    b50, b99 = ms_summary(bare)
    c50, c99 = ms_summary(repeats)
    cb50, _ = ms_summary(cached_bare)
    return {
        "resolve_p50_ms": q50,
        "resolve_p99_ms": q99,
        "bare_p50_ms": b50,
        "bare_p99_ms": b99,
        "ratio_p50": round(q50 / b50, 3),
        "ratio_p99": round(q99 / b99, 3),
        "cached_p50_ms": c50,
        "cached_p99_ms": c99,
        "ratio_cached_p50": round(c50 / cb50, 3),
        "samples": len(queries),
        "cached_samples": len(repeats),
    }


# The whole bench


def run(n: int, warmup: int, max_query_seconds: float, inprocess_seconds: float) -> dict[str, Any]:
    result: dict[str, Any] = {
        "references": 0,
        "correct": 0,
        "accuracy": None,
        "resolve_p50_ms": None,
        "resolve_p99_ms": None,
        "bare_p50_ms": None,
        "bare_p99_ms": None,
        "ratio_p50": None,
        "ratio_p99": None,
        "cached_p50_ms": None,
        "cached_p99_ms": None,
        "ratio_cached_p50": None,
        "inprocess_p50_ms": None,
        "inprocess_p99_ms": None,
        "samples": 0,
        "cached_samples": 0,
        "warmup": warmup,
        "incorrect": [],
    }
    errors: list[str] = []
    steps = (
        ("accuracy", accuracy),
        ("in-process", lambda: _inprocess(inprocess_seconds, warmup)),
        ("service", lambda: service_latency(n, warmup, max_query_seconds)),
    )
    for _, measure in steps:
        try:
            result |= measure()
        except BenchError as exc:
            errors.append(str(exc))
            progress(f"error: {exc}")
    result["errors"] = errors
    result["notes"] = {
        **machine(),
        "accuracy": "cases of tests/corpus/resolver/references.yaml passing its runner, resolved in-process",
        "plan": "10 steps: navigate_to, pick, navigate_to, place, detect, say, navigate_to, pick, look_at, wait",
        "resolve": "plan/resolve to a resolver process started by the Supervisor; a distinct plan each query "
        "(its wait duration), so the translation cache never answers",
        "cached": "plan/resolve with one plan repeated: answered by the translation cache",
        "bare": "bare Zenoh get on bench/raw_echo/resolver, echoed by the same resolver process and session, "
        "with as many bytes as the plan",
        "inprocess": "Resolver.resolve of the bench plan in this process, each timed alone, after warm-up",
        "world": "household, world file only: no sim, so no perception and no odometry",
        "order": "interleaved with the bare echo, alternating first call",
        "request_bytes": len(runtime.encode(bench_plan())),
    }
    return result


def _inprocess(seconds: float, warmup: int) -> dict[str, Any]:
    progress(f"resolving the bench plan in-process for {seconds:g} s")
    p50, p99 = ms_summary(inprocess_ms(seconds, warmup))
    return {"inprocess_p50_ms": p50, "inprocess_p99_ms": p99}


def print_table(result: dict[str, Any]) -> None:
    from rich.console import Console
    from rich.table import Table

    def show(value: Any, unit: str = "") -> str:
        return "-" if value is None else f"{value:,.3f}{unit}" if isinstance(value, float) else f"{value}{unit}"

    def pair(key: str) -> str:
        return f"{show(result[f'{key}_p50_ms'])} / {show(result[f'{key}_p99_ms'])}"

    table = Table(title=f"resolver ({result['samples']} round trips of each kind, {result['warmup']} warm-up)")
    table.add_column("")
    table.add_column("measured", justify="right")
    table.add_row("accuracy", f"{show(result['accuracy'])} ({result['correct']}/{result['references']})")
    table.add_row("in-process resolve p50 / p99 ms", pair("inprocess"))
    table.add_row("plan/resolve p50 / p99 ms", pair("resolve"))
    table.add_row("plan/resolve cached p50 / p99 ms", pair("cached"))
    table.add_row("bare zenoh p50 / p99 ms", pair("bare"))
    table.add_row("ratio p50 (cached)", f"{show(result['ratio_p50'], 'x')} ({show(result['ratio_cached_p50'], 'x')})")
    console = Console()
    console.print(table)
    for line in result["incorrect"]:
        console.print(f"[yellow]incorrect:[/] {line}", markup=True, highlight=False)
    for error in result["errors"]:
        console.print(f"[red]error:[/] {error}", markup=True, highlight=False)


def main(argv: list[str] | None = None) -> None:
    command_line(
        "bench.resolver",
        __doc__ or "",
        lambda seconds, n, warmup, max_query: run(n, warmup, max_query, seconds),
        print_table,
        argv,
        seconds=3.0,
        seconds_help="in-process resolving time",
    )


if __name__ == "__main__":
    main()
