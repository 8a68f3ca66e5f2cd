"""The recorder under load: 1 KB JSON messages at 40 kHz for 30 s, counted as published and as found in the file.

    python -m bench.recorder --json        one JSON object on stdout, progress on stderr
    python -m bench.recorder               a short table with the goals

Measured: this process puts 1024-byte JSON objects (a sequence number and a padding string of
fresh random base64, so zstd cannot shrink the stream to nothing) raw on `bench/recorder_load` at a
fixed rate (`--rate`, default 40,000 a second: the goal) for `--duration` seconds (default 30; less
only with `--quick`). The puts follow a deadline schedule on perf_counter: each wake-up (at most one per TICK)
puts every message due by then, so the rate holds however coarse sleep is. The recorder is a real
process started by the Supervisor on a robot name and ports of its own, writing into a temporary
directory. After the last put the recorder's status is polled until its count stops rising
(`drain_s`: how far behind it was), then it gets SIGTERM, which finishes the file, and its exit is
awaited. `recorded` counts the messages on the bench's key in the finished file, read back with
services.recorder.reader.read_recording, by their sequence numbers: each of those published once,
so a message recorded twice cannot make up for one lost (`recorded_extra` counts those and any that
is none of the load's, an error); `lost` = `published` - `recorded`. `rate_hz` = published
over the time from the first deadline to the end of the last put plus one period; `max_late_ms` is
the latest any wake-up came against its deadline. The rate goal allows RATE_TOLERANCE: a stall of
this process near the end (other processes on the CPU) makes the last puts late. `goals_met` also
asks for `duration_s` of at least 30 s: a `--quick` run does not meet the goal.

Baseline, in the same run, before the recorder: the same stream (`--baseline-duration`, default
10 s) to a bare Zenoh subscriber on `tether/<robot>/**` in a process of its own (this module with
`--count`), on a session configured as the recorder's (NodeSettings.zenoh), that only counts
samples under a lock: `baseline_received`, `baseline_lost`.

Puts use CongestionControl.BLOCK, not Zenoh's default DROP (`--congestion drop` measures with it):
with DROP, Zenoh drops a put when the publisher's queue is full (the receiver or this process briefly
without a CPU), before it reaches any subscriber. On a 2-core machine shared with a running stack
that lost 0.01-0.5% of messages, to the bare counting subscriber and to the recorder alike. With
BLOCK nothing is dropped in transport; a recorder too slow for the rate would slow the puts instead,
and show as `rate_hz` below the goal and a growing `max_late_ms`.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import itertools
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import msgspec
import zenoh

from bench.service import (
    READY_TIMEOUT,
    STOP_TIMEOUT,
    BenchError,
    bench_main,
    bench_settings,
    bounded,
    last_line,
    measured,
    notes,
    print_rows,
    reporter,
    running_stack,
    show,
)
from bench.transport import stop_server
from schemas import keys
from schemas.trace import RecorderStatus
from schemas.world import Empty
from services import runtime
from services.errors import CallError
from services.recorder.reader import read_recording
from services.runtime import Node, NodeSettings

PROG = "bench.recorder"
GOALS = {"goal_rate_hz": 40_000.0, "goal_lost": 0}
# The rate may fall this far short of the goal: the last puts can be late (150 ms in 30 s).
RATE_TOLERANCE = 0.005
MIN_DURATION = 30.0
PAYLOAD_BYTES = 1024
TICK = 0.001  # the publisher wakes at most this often and puts every message due
DRAIN_POLL = 0.25  # seconds between looks at the subscriber's count after the last put
DRAIN_TIMEOUT = 60.0
COUNTER = "bench-counter"  # the baseline's liveliness name
progress = reporter(PROG)


def payload(seq: int, size: int = PAYLOAD_BYTES) -> bytes:
    """A JSON object of exactly `size` bytes: the sequence number and random base64 padding."""
    head = b'{"seq":%d,"pad":"' % seq
    pad = size - len(head) - 2
    return head + base64.b64encode(os.urandom(pad * 3 // 4 + 3))[:pad] + b'"}'


# The stream


@dataclass(frozen=True)
class Published:
    count: int
    seconds: float  # from the first put's deadline to the end of the last put
    max_late_ms: float

    @property
    def rate_hz(self) -> float:
        return self.count / self.seconds if self.seconds > 0 else 0.0


def publish(put: Callable[[bytes], None], rate_hz: float, seconds: float) -> Published:
    """round(rate_hz * seconds) messages, message i due at start + i / rate_hz."""
    total = max(1, round(rate_hz * seconds))
    sent, max_late = 0, 0.0
    start = time.perf_counter()
    while sent < total:
        woke = time.perf_counter()
        due = min(total, int((woke - start) * rate_hz) + 1)
        if due > sent:
            max_late = max(max_late, woke - (start + sent / rate_hz))
        while sent < due:
            put(payload(sent))
            sent += 1
        next_due = start + sent / rate_hz
        time.sleep(max(0.0, max(next_due, woke + TICK) - time.perf_counter()))
    # The last message's period counts: `total` messages fill total / rate_hz seconds on schedule.
    elapsed = time.perf_counter() - start + 1.0 / rate_hz
    return Published(sent, elapsed, max_late * 1000)


CONGESTION = {"block": zenoh.CongestionControl.BLOCK, "drop": zenoh.CongestionControl.DROP}


def stream(node: Node, rate_hz: float, seconds: float, congestion: str) -> Published:
    """The load, put raw on `load_key`."""
    publisher = node.session.declare_publisher(
        keys.bench_load_key(node.robot), congestion_control=CONGESTION[congestion]
    )
    try:
        return publish(publisher.put, rate_hz, seconds)
    finally:
        publisher.undeclare()


def drained(count: Callable[[], int], target: int) -> tuple[int, float]:
    """Poll `count()` until it reaches `target` or stops growing (the subscriber has everything it
    will get): (the last count, seconds it took)."""
    started = time.monotonic()
    last = count()
    while last < target and time.monotonic() - started < DRAIN_TIMEOUT:
        time.sleep(DRAIN_POLL)
        now = count()
        if now <= last:
            return now, time.monotonic() - started - DRAIN_POLL
        last = now
    return last, time.monotonic() - started


class Seq(msgspec.Struct):
    """What the count reads of a load message."""

    seq: int


class LoadFound:
    """The load's messages found in a recording, each of the `published` sequence numbers once."""

    def __init__(self, published: int) -> None:
        self._seen = bytearray(published)
        self._decode = msgspec.json.Decoder(Seq).decode
        self.found = 0
        self.extra = 0  # a message found again, or one that is none of the load's

    def add(self, data: bytes) -> None:
        try:
            seq = self._decode(data).seq
        except msgspec.DecodeError:
            self.extra += 1
            return
        if 0 <= seq < len(self._seen) and not self._seen[seq]:
            self._seen[seq] = 1
            self.found += 1
        else:
            self.extra += 1


# The baseline: a bare Zenoh subscriber that counts


def count(settings: NodeSettings) -> None:
    """The baseline child process: count samples under the robot's prefix until SIGINT/SIGTERM."""
    stop = runtime.stop_event()
    lock = threading.Lock()
    received = 0

    def on_sample(_sample: zenoh.Sample) -> None:
        nonlocal received
        with lock:
            received += 1

    def answer(query: zenoh.Query) -> None:
        try:
            with lock:
                query.reply(keys.bench_count_key(settings.robot), str(received).encode())
        finally:
            query.drop()

    with zenoh.open(settings.zenoh("recorder")) as session:
        subscriber = session.declare_subscriber(keys.all_keys(settings.robot), on_sample)
        queryable = session.declare_queryable(keys.bench_count_key(settings.robot), answer)
        token = session.liveliness().declare_token(keys.alive_key(settings.robot, COUNTER))
        stop.wait()
        for item in (token, queryable, subscriber):
            item.undeclare()


def counted(node: Node) -> int:
    for reply in node.session.get(keys.bench_count_key(node.robot), timeout=5.0):
        if reply.ok is not None:
            return int(reply.ok.payload.to_string())
    raise BenchError("the baseline counter did not answer")


@contextlib.contextmanager
def running_counter(settings: NodeSettings, log: IO[bytes]) -> Iterator[tuple[Node, subprocess.Popen[bytes]]]:
    """The counter as a child process, with a Node that puts to it once it is alive; always stopped."""
    env = {**os.environ, "TETHER_ROBOT": settings.robot, "TETHER_BASE_PORT": str(settings.base_port)}
    proc = subprocess.Popen(
        [sys.executable, "-m", PROG, "--count"], env=env, stdout=log, stderr=log, start_new_session=True
    )
    try:
        with Node("cli", settings) as node:
            if node.wait_alive({COUNTER}, timeout=READY_TIMEOUT):
                log.seek(0)
                why = f"exited with code {proc.poll()}" if proc.poll() is not None else "not alive"
                raise BenchError(f"baseline counter {why}: {last_line(log.read().decode(errors='replace'))}")
            yield node, proc
    finally:
        stop_server(proc)


def baseline(rate_hz: float, seconds: float, congestion: str) -> dict[str, Any]:
    settings = bench_settings("recorder-baseline")
    progress(
        f"baseline: {rate_hz:g} msg/s for {seconds:g} s to a bare counting subscriber (base port {settings.base_port})"
    )
    with tempfile.TemporaryFile() as log, running_counter(settings, log) as (node, proc):
        sent = stream(node, rate_hz, seconds, congestion)
        received, drain_s = drained(lambda: counted(node), sent.count)
        cpu = cpu_seconds(proc.pid)
    progress(f"baseline: {received} of {sent.count} received at {sent.rate_hz:,.0f} msg/s")
    return {
        "baseline_published": sent.count,
        "baseline_received": received,
        "baseline_lost": sent.count - received,
        "baseline_rate_hz": round(sent.rate_hz, 1),
        "baseline_duration_s": round(sent.seconds, 3),
        "baseline_drain_s": round(drain_s, 3),
        "baseline_cpu_s": None if cpu is None else round(cpu, 2),
    }


# The recorder


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of a running process so far."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def recorder(rate_hz: float, seconds: float, congestion: str) -> dict[str, Any]:
    settings = bench_settings("recorder-recorder")
    with tempfile.TemporaryDirectory(prefix="bench-recorder-") as tmp:
        output = Path(tmp) / "recordings"
        config = {"recorder": {"output_dir": str(output)}}
        progress(f"recorder: starting it (robot {settings.robot}, base port {settings.base_port})")
        with running_stack(("recorder",), settings, Path(tmp), progress, config=config) as stack:
            node, supervisor = stack.node, stack.supervisor

            def status() -> RecorderStatus:
                try:
                    return node.call(keys.RECORDER_STATUS, Empty(), timeout=5.0)
                except CallError as exc:
                    raise BenchError(f"recorder/status: {exc.error.message}") from None

            before = status().messages
            polls = itertools.count(1)

            def load_so_far() -> int:
                # Each status query is recorded too (its trace, after the reply): a lower bound.
                return status().messages - before - next(polls)

            progress(f"recorder: {rate_hz:g} msg/s for {seconds:g} s")
            sent = stream(node, rate_hz, seconds, congestion)
            _, drain_s = drained(load_so_far, sent.count)
            final = status()
            cpu = cpu_seconds(supervisor.procs["recorder"].pid)
            progress("recorder: stopping it (SIGTERM)")
            code = supervisor.stop("recorder", timeout=STOP_TIMEOUT)
            if code != 0:
                raise BenchError(f"the recorder exited with code {code}: {last_line(supervisor.log_tail('recorder'))}")
        progress(f"recorder: reading back {', '.join(final.files)}")
        load = LoadFound(sent.count)
        file_bytes = 0
        for name in final.files:
            path = Path(name)
            file_bytes += path.stat().st_size
            recording = read_recording(path, keep=lambda key: key == keys.bench_load_key(settings.robot))
            if not recording.complete:
                raise BenchError(f"{path}: {recording.problem}")
            for message in recording.messages:
                load.add(message.data)
    progress(f"recorder: {load.found} of {sent.count} recorded at {sent.rate_hz:,.0f} msg/s")
    errors = [f"{load.extra} messages on the load's key recorded twice or not the load's"] if load.extra else []
    return {
        "published": sent.count,
        "recorded": load.found,
        "recorded_extra": load.extra,
        "lost": sent.count - load.found,
        "rate_hz": round(sent.rate_hz, 1),
        "duration_s": round(sent.seconds, 3),
        "max_late_ms": round(sent.max_late_ms, 3),
        "drain_s": round(drain_s, 3),
        "recorder_dropped": final.dropped,
        "recorder_cpu_s": None if cpu is None else round(cpu, 2),
        "files": len(final.files),
        "file_bytes": file_bytes,
        "errors": errors,
    }


def goals_met(result: dict[str, Any]) -> dict[str, bool]:
    rate, lost, duration = result.get("rate_hz"), result.get("lost"), result.get("duration_s")
    return {
        "rate_hz": rate is not None and rate >= GOALS["goal_rate_hz"] * (1 - RATE_TOLERANCE),
        "lost": lost is not None and lost <= GOALS["goal_lost"],
        # The goal's rate held for 30 s, not a --quick run's few.
        "duration_s": duration is not None and duration >= MIN_DURATION,
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    if args.duration < MIN_DURATION and not args.quick:
        raise SystemExit(
            f"{PROG}: --duration {args.duration:g} is below {MIN_DURATION:g} s; add --quick to run it anyway"
        )
    defaults: dict[str, Any] = {
        "published": 0,
        "recorded": 0,
        "recorded_extra": None,
        "lost": None,
        "rate_hz": None,
        "duration_s": None,
        "baseline_published": 0,
        "baseline_received": 0,
        "baseline_lost": None,
        "baseline_rate_hz": None,
        **GOALS,
    }

    def bench() -> dict[str, Any]:
        return {
            **baseline(args.rate, args.baseline_duration, args.congestion),
            **recorder(args.rate, args.duration, args.congestion),
        }

    result = measured(defaults, bench, progress)
    result["goals_met"] = goals_met(result)
    result["notes"] = notes(
        payload_bytes=PAYLOAD_BYTES,
        payload="a JSON object: seq and random base64 padding (zstd cannot shrink it much)",
        congestion_control=args.congestion,
        schedule=f"deadline on perf_counter; each wake-up (at most every {TICK * 1000:g} ms) puts all messages due",
        baseline="bare Zenoh subscriber on tether/<robot>/** counting under a lock, own process, run first",
        recorder="tether run recorder via the Supervisor: zstd chunks of 1 MiB, flushed every second",
        quick=args.quick,
    )
    return result


def print_table(result: dict[str, Any]) -> None:
    met = result["goals_met"]

    goal_rate, tolerance = GOALS["goal_rate_hz"], f"{RATE_TOLERANCE:.1%}"

    def mark(ok: bool) -> str:
        return "met" if ok else "NOT met"

    rows = [
        (
            "publish rate (msg/s)",
            show(result["rate_hz"]),
            f">= {goal_rate:,.0f} (less {tolerance}): {mark(met['rate_hz'])}",
        ),
        ("published / recorded", f"{result['published']} / {result['recorded']}", ""),
        ("lost", show(result["lost"]), f"{GOALS['goal_lost']}: {mark(met['lost'])}"),
        ("latest put against its deadline (ms)", show(result.get("max_late_ms")), ""),
        ("drain after the last put (s)", show(result.get("drain_s")), ""),
        ("recorder CPU (s)", show(result.get("recorder_cpu_s")), ""),
        ("baseline rate (msg/s)", show(result["baseline_rate_hz"]), ""),
        ("baseline published / received", f"{result['baseline_published']} / {result['baseline_received']}", ""),
        ("baseline lost", show(result["baseline_lost"]), ""),
        ("baseline CPU (s)", show(result.get("baseline_cpu_s")), ""),
    ]
    print_rows(f"recorder under {PAYLOAD_BYTES}-byte messages ({show(result['duration_s'])} s)", rows, result["errors"])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--rate", type=bounded(float, 0.0, 100_000.0, open_low=True), default=40_000.0, help="messages a second"
    )
    parser.add_argument(
        "--duration",
        type=bounded(float, 0.0, 600.0, open_low=True),
        default=MIN_DURATION,
        help=f"seconds of load on the recorder (at least {MIN_DURATION:g} unless --quick)",
    )
    parser.add_argument(
        "--baseline-duration",
        type=bounded(float, 0.0, 600.0, open_low=True),
        default=10.0,
        help="seconds of load on the bare counting subscriber",
    )
    parser.add_argument(
        "--congestion",
        choices=sorted(CONGESTION),
        default="block",
        help="the publisher's congestion control (drop: Zenoh's default, loses messages when a queue is full)",
    )
    parser.add_argument("--quick", action="store_true", help="allow a --duration under 30 s, for development")
    parser.add_argument("--count", action="store_true", help=argparse.SUPPRESS)  # the baseline child process


def main(argv: list[str] | None = None) -> None:
    if (sys.argv[1:] if argv is None else argv) == ["--count"]:
        runtime.configure_logging("WARNING")
        count(NodeSettings.from_env())
        return
    bench_main(PROG, __doc__ or "", add_arguments, run, print_table, argv)


if __name__ == "__main__":
    main()
