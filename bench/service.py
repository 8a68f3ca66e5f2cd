"""A real service process for a bench: started by the Supervisor on its own robot and ports, echo baseline included.

The service is started with TETHER_BENCH_ECHO=1 (services.runtime.BENCH_ECHO_ENV), so the same
process and session also answer the bare Zenoh echo of `bench.transport`: the baseline each query is
compared with, interleaved with it.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import statistics
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from bench.transport import bare_echo, free_base_port, interleaved, percentile
from services import runtime
from services.runtime import Node, NodeSettings
from tether.supervisor import Supervisor

READY_TIMEOUT = 30.0
STOP_TIMEOUT = 5.0

Progress = Callable[[str], None]
# Round trips of each kind a bench may be asked for.
MAX_N = 20_000


class BenchError(Exception):
    """A part of the bench could not run; the message says which and why."""


def ms_summary(ms: list[float]) -> tuple[float, float]:
    """Median and p99, in ms, rounded for the JSON."""
    return round(statistics.median(ms), 4), round(percentile(ms, 99), 4)


def bench_settings(bench: str) -> NodeSettings:
    """A robot name and ports of this bench's own, so it never talks to a running stack."""
    # The service gets our settings only: an inherited Zenoh config file would point it at other peers.
    os.environ.pop("TETHER_ZENOH_CONFIG", None)
    base_port = int(os.environ.get("TETHER_BASE_PORT") or free_base_port())
    return NodeSettings(robot=f"bench-{bench}-{os.getpid()}", base_port=base_port)


@contextlib.contextmanager
def running_service(service: str, settings: NodeSettings, log_dir: Path, progress: Progress) -> Iterator[Node]:
    """`service` as a child process, with a client Node once it is alive; always stopped."""
    supervisor = Supervisor(settings, log_dir, extra_env={runtime.BENCH_ECHO_ENV: "1"})
    node: Node | None = None
    try:
        supervisor.start(service)
        node = Node("cli", settings)
        wait_ready(node, supervisor, service, progress)
        yield node
    finally:
        # A second Ctrl-C must not leave the child running: stopping takes at most STOP_TIMEOUT + 10 s.
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            if node is not None:
                node.close()
            supervisor.stop_all(timeout=STOP_TIMEOUT)
        finally:
            signal.signal(signal.SIGINT, previous)


def wait_ready(node: Node, supervisor: Supervisor, service: str, progress: Progress) -> None:
    """Until the service holds its liveliness token; a service that exits is reported at once."""
    deadline = time.monotonic() + READY_TIMEOUT
    while node.wait_alive({service}, timeout=0.5):
        code = supervisor.exited().get(service)
        if code is None and time.monotonic() < deadline:
            continue
        why = f"not alive within {READY_TIMEOUT:g} s" if code is None else f"exited with code {code}"
        tail = supervisor.log_tail(service)
        progress(f"{service} service log:\n{tail}")
        raise BenchError(f"{service} service {why}: {last_line(tail)}")


def last_line(log: str) -> str:
    """The last line of a log with text on it: the exception of a traceback, without rich's box drawing."""
    lines = [line.strip(" \u2502\u2570\u2500\u256f\u256d\u256e") for line in log.splitlines()]
    return next((line for line in reversed(lines) if line), "no output")


def against_echo(
    node: Node, payload: bytes, query: Callable[[], None], n: int, warmup: int, max_seconds: float
) -> tuple[list[float], list[float]]:
    """Interleaved round trips in ms: (bare echo carrying `payload`, `query`)."""
    try:
        return interleaved(bare_echo(node, payload), query, n, warmup, max_seconds)
    except RuntimeError as exc:  # the bare echo failed or did not answer
        raise BenchError(str(exc)) from None


def command_line(
    prog: str,
    doc: str,
    run: Callable[[float, int, int, float], dict[str, Any]],
    print_table: Callable[[dict[str, Any]], None],
    progress: Progress,
    argv: list[str] | None,
    *,
    seconds: float,
    seconds_help: str,
) -> None:
    """The command line every service bench shares: `run(seconds, n, warmup, max_query_seconds)`
    gives the result, printed as one JSON object with --json, else as a table; exit 1 on errors."""
    parser = argparse.ArgumentParser(prog=f"python -m {prog}", description=doc.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--seconds", type=float, default=seconds, help=seconds_help)
    parser.add_argument("--n", type=int, default=1000, help=f"round trips of each kind (10..{MAX_N})")
    parser.add_argument(
        "--warmup", type=int, default=50, help="in-process runs and round trips of each kind not counted"
    )
    parser.add_argument("--max-query-seconds", type=float, default=15.0, help="stop each kind of round trip after this")
    args = parser.parse_args(argv)
    if not 10 <= args.n <= MAX_N:
        parser.error(f"--n must be between 10 and {MAX_N}")
    if not 0 < args.seconds <= 600 or not 0 < args.max_query_seconds <= 600:
        parser.error("--seconds and --max-query-seconds must be in (0, 600]")
    runtime.configure_logging("WARNING")
    # SIGTERM unwinds like Ctrl-C, so the service process is stopped either way.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        result = run(args.seconds, args.n, max(0, args.warmup), args.max_query_seconds)
    except KeyboardInterrupt:
        progress("interrupted")
        sys.exit(130)
    if args.json:
        print(json.dumps(result))
    else:
        print_table(result)
    if result["errors"]:
        sys.exit(1)
