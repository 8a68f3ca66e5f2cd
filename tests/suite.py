"""`make test`'s pytest run, sized for a 2-core machine: `python -m tests.suite [--typecheck] [PYTEST ARGS]`.

First, two pytest runs at once:
- the tests marked `realtime` (they bound halts, report rates and watchdogs in wall seconds), one at a
  time at normal priority; their output goes to a file and is shown when they end;
- the tests that start services (tests/integration, all but those marked realtime or alone) on three
  pytest-xdist workers (STACK_WORKERS) (`--dist loadscope`: whole modules, so a module's shared stack stays on one
  worker, in the order tests/conftest.py explains), at low priority (nice 15), their output on the
  terminal.
Then the tests marked `alone` (realtime too: the multi-host tests, two robots' stacks in network
namespaces with a router and link proxies, the ROS 2 stand-in's, whose dead-man signal comes from
the test process at 20 Hz, and the robot contract's, whose safety heartbeat a child process plays,
tests/robot_contract/played_safety.py) one at a time, without other stacks: with the parallel part
beside them, their robots' heartbeats or signals came late now and then. That held for these
modules beside each other too (two workers: the multi-host module on one, the stand-in's and the
contract's on the other): five of six such runs passed, one lost a contract test (no heartbeat for
200 ms). One at a time they take about two and a half minutes (the multi-host sims at four times
real time) and leave more than a core idle (59 % of the machine, measured with vmstat).
That idle CPU runs the tests marked `unit` (every test under tests/unit but those marked realtime,
tests/conftest.py: in the test process, without a stack of services; about 130 s of CPU) on two
workers, in a scheduling group of their own at the lowest weight (their own session, its autogroup at
nice 19), so that whatever the tests marked alone and their services want comes first. Measured on
2026-11-27 in three runs: the tests marked alone took 132 to 144 s beside them (132 to 142 s without),
and the unit tests ended about when they did (134 to 137 s). Before, the unit tests ran in the
parallel part, on the two cores its stacks keep busy (85 % of the machine): that part took 347 s, and
275 s without them. The whole suite in a working tree: 411 and 414 s, against about 490 s. A unit
test that bounds wall time is marked realtime; one that bounds work measures CPU time
(time.thread_time).
From the start, beside all of these, the tests marked `idle` (the modules of tests/unit that only
compute, tests/conftest.py IDLE_UNIT: the parser's properties and corpora, the link audit, ...;
about 45 s of CPU) run in one pytest process, in a scheduling group of its own at the lowest weight
and under SCHED_IDLE in it: only on CPU nothing else wants, of which the parallel part leaves plenty
(vmstat, 2026-11-28: 10.6 % of the machine idle on average with these tests beside it, none for a
minute at its start, up to half near its end). Measured with the parser's modules, the link audit
and the incident store (44 s of CPU; the store waits on the clock in one test and stays in the unit
tests' run): they ran in 82 s beside the parallel part, which took 283 s (272 to 294 s without
them); in the unit tests' run, their CPU had made that run outlast the tests marked alone by 30 to
50 s (a fresh clone's CI run then: the tests marked idle done after 176 s, the unit tests after 126
s, before the tests marked alone, 138 s). That run and the next had them (and mypy) under SCHED_IDLE
in the suite's own group: idle only within it, and when pytest waited the group's share, as much as
a service's, went to them. The parallel part took 330 and 341 s (305 before), and a realtime test's
goal was once aborted. With --typecheck, mypy runs from the start too, in a group of its own like
them (about 17 s of CPU), its output shown after theirs.

Most wall-clock tests mostly wait (a real-time sim, an outage, a watchdog); the rest mostly compute.
Run side by side, the waiting fills the computing's idle time, and the scheduler hands the CPU to the
wall-clock tests' processes the moment they wake. Stacks of the parallel part run with a looser
heartbeat bound (tests/integration/conftest.py, LOADED_MACHINE_HEARTBEAT) for the same reason.
Nice 15 holds back the parallel part's pytest workers only: Linux's autogroup scheduling makes each
service, started in a session of its own (tether.supervisor), a group of its own at nice 0, whatever
its process's nice. Tried on 2026-11-27 and dropped: the tests marked alone beside the parallel
part, with and without the parallel part's services' groups at nice 15 too. Both runs were red: a
multi-host watchdog bound and contract tests failed beside the parallel part, and with the groups
at nice 15 its own timed tests starved (a deployment's 0.2 s heartbeat, a 1 s arm plan). They took
555 and 584 s, against about 600 s for the parts one after the other.
The exit status is the first failing run's (pytest's codes, then mypy's), or 0. Last comes a summary: each
run's status and the tests that failed, read from the JUnit XML each pytest run writes; CI keeps the end of
the output, and a failure shown only in the first run's part was not in it.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO
from xml.etree import ElementTree

from tests.conftest import IDLE_UNIT, INTEGRATION, REALTIME_UNIT
from tests.conftest import UNIT as UNIT_TESTS

# pytest-xdist workers of the unit tests' run (two cores, computing).
WORKERS = 2
# Workers of the parallel part: three on two cores, since its stacks mostly wait (real-time and fast
# sims, outages, watchdogs, services starting). Measured on 2026-11-29 without the runs beside it:
# on two workers it took 220.6 s and left 42 % of the machine idle (vmstat), on three 170.8 s with
# 27 % idle; in the whole suite, 173.6 s against 233 s, the suite 296 s against 353 to 365 s, the
# tests marked realtime beside it as quick as before (84 s against 82), those marked idle 95 s
# against 88. (Three were tried on 2026-11-27 too and made no difference then, 275.0 s against 276.1;
# what this part holds and what runs beside it have changed since.)
STACK_WORKERS = 3
# Low priority for the parallel part: at nice 15 a process weighs 1/28 of one at nice 0.
NICE = 15
# The unit tests' group, beside the tests marked alone: at nice 19 it weighs 15 against a service's 1024.
LOWEST = 19
# pytest's exit status when a selection holds no test: a run of files without such tests is fine.
NO_TESTS = 5
# Set, Python and pytest write no bytecode, so pytest's assertion rewriting is not kept.
WRITE_NO_BYTECODE = "PYTHONDONTWRITEBYTECODE"
# `make typecheck`'s check (its settings in pyproject.toml).
MYPY = [sys.executable, "-m", "mypy"]
# The five selections, each test in one (the markers are in pyproject.toml; tests/conftest.py marks
# tests/unit `unit`, and its modules that only compute `idle` too).
STACKS = "not realtime and not unit and not alone"
REALTIME = "realtime and not alone"
IDLE = "idle and not realtime"
UNIT = "unit and not realtime and not alone and not idle"
ALONE = "alone"
# Where each selection's tests are, when the suite runs them all (`python -m tests.suite` with no
# paths): a pytest process imports every module it is given to collect it, about 8 s of CPU for all
# of tests (20 on a fresh clone, rewriting the asserts), of which tests/unit's modules take 5 (mcp,
# matplotlib, hypothesis, the ROS 2 typestores, the worlds). No test under tests/unit is marked alone,
# and the tests marked realtime but not alone are in tests/integration or REALTIME_UNIT's modules
# (tests/conftest.py refuses others); none outside tests/unit is marked unit.
BUT_UNIT = ["tests", f"--ignore={UNIT_TESTS}"]
ROOTS = {
    STACKS: BUT_UNIT,
    REALTIME: [INTEGRATION, *REALTIME_UNIT],
    IDLE: list(IDLE_UNIT),
    UNIT: [UNIT_TESTS],
    ALONE: BUT_UNIT,
}


def pytest(*args: str) -> list[str]:
    """pytest, quiet, listing each run's 15 slowest tests at the end (the suite's time is watched)."""
    return [sys.executable, "-m", "pytest", "-q", "--durations=15", *args]


def on_workers(*args: str, workers: int = WORKERS) -> list[str]:
    """pytest on `workers` pytest-xdist workers, each taking whole modules (tests/conftest.py)."""
    return pytest("-n", str(workers), "--dist", "loadscope", *args)


def idle() -> None:
    """In a child before exec: run only on CPU nothing else wants."""
    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))


def lowest() -> None:
    """In a child of its own session before exec: that session's autogroup at the lowest weight. A
    process's own nice counts only inside its group; without autogroup scheduling it is all there is."""
    with contextlib.suppress(OSError):  # no /proc/self/autogroup: the kernel schedules no autogroups
        Path("/proc/self/autogroup").write_text(str(LOWEST))
    os.nice(LOWEST)


def idlest() -> None:
    """In a child of its own session before exec: its autogroup at the lowest weight, and in it, only
    the CPU nothing else wants. SCHED_IDLE alone would not do: it is idle only within its autogroup,
    and a group of its own, or the suite's while pytest waits, weighs as much as any service's."""
    lowest()
    idle()


def shown(title: str, log: IO[bytes]) -> None:
    """A run's output, kept in `log` while it ran beside another, under `title`."""
    print(f"\n== {title} ==", flush=True)
    log.seek(0)
    sys.stdout.buffer.write(log.read())
    sys.stdout.flush()


def stopped(process: subprocess.Popen[bytes] | None, group: bool = False) -> None:
    """`process` (with `group`, its whole session) told to stop if it still runs, and waited for."""
    if process is None or process.poll() is not None:
        return
    if group:
        os.killpg(process.pid, signal.SIGTERM)
    else:
        process.terminate()
    process.wait()


def interrupted(signum: int, frame: object) -> None:
    """SIGTERM or SIGHUP (a CI job cancelled, a terminal closed): the runs are stopped as on Ctrl-C. The
    unit tests' run has a session of its own, and no signal sent to this one reaches it."""
    raise SystemExit(128 + signum)


def failures(report: Path) -> list[str]:
    """`CLASS::NAME: MESSAGE` of each test that failed or errored in the JUnit XML `report`, which pytest
    wrote (nothing if it did not)."""
    try:
        root = ElementTree.parse(report).getroot()
    except (OSError, ElementTree.ParseError):
        return []
    found = []
    for case in root.iter("testcase"):
        for bad in [*case.iter("failure"), *case.iter("error")]:
            message = " ".join((bad.get("message") or "").split())[:300]
            found.append(f"{case.get('classname')}::{case.get('name')}: {message}")
    return found


def summary(results: list[tuple[str, int, Path | None]]) -> None:
    """Each run's (title, exit status, JUnit XML report or None) and the tests that failed in it."""
    print("\n== summary ==", flush=True)
    for title, code, report in results:
        status = {0: "passed", NO_TESTS: "no tests"}.get(code, f"failed (exit {code})")
        print(f"{title}: {status}")
        for line in failures(report) if report is not None else []:
            print(f"  FAILED {line}")
    sys.stdout.flush()


def main(argv: list[str]) -> int:
    for signum in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, interrupted)
    with tempfile.TemporaryDirectory(prefix="tether-suite-") as reports:
        return run(argv, Path(reports))


def run(argv: list[str], reports: Path) -> int:
    """The runs, their JUnit XML reports in `reports`."""
    typecheck = argv[:1] == ["--typecheck"]
    extra = argv[1:] if typecheck else argv

    def given(selection: str) -> list[str]:
        """What pytest is told to collect for `selection`: what the command line gave, or its ROOTS."""
        return extra or ROOTS[selection]

    # A band of ports (tests/sessions.py) for each worker, and one after theirs for the realtime runs.
    # pytest keeps each test module as it rewrote its asserts in __pycache__ (beside Python's own
    # bytecode, which compileall writes; pytest's is its own), unless bytecode is not to be written
    # (PYTHONDONTWRITEBYTECODE, set on this machine): then every pytest process rewrites every
    # module again, and collecting the suite took 13 s of CPU instead of 6. The first pytest
    # processes of a fresh clone write it; those after them, and every later `make test`, reuse it.
    env = {name: value for name, value in os.environ.items() if name != WRITE_NO_BYTECODE}
    env |= {"TETHER_TEST_PORT_BANDS": str(STACK_WORKERS + 1)}
    alone = env | {"TETHER_TEST_PORT_BAND": str(STACK_WORKERS)}
    junit = {name: reports / f"{name}.xml" for name in ("realtime", "parallel", "alone", "unit", "idle")}
    with (
        tempfile.NamedTemporaryFile("w+b", prefix="tether-idle-", suffix=".log") as idle_log,
        tempfile.TemporaryFile("w+b") as typecheck_log,
    ):
        # From the start, on the CPU the stacks leave idle: none of their work waits on the clock.
        computing = subprocess.Popen(
            pytest("-m", IDLE, "-p", "no:cacheprovider", f"--junitxml={junit['idle']}", *given(IDLE)),
            stdout=idle_log,
            stderr=idle_log,
            start_new_session=True,
            preexec_fn=idlest,
            env=env,
        )
        print(f"tests marked idle: running alongside on idle CPU, output in {idle_log.name}", flush=True)
        mypy = (
            subprocess.Popen(
                MYPY, stdout=typecheck_log, stderr=typecheck_log, start_new_session=True, preexec_fn=idlest
            )
            if typecheck
            else None
        )
        try:
            results = runs(given, env, alone, junit)
            if computing.poll() is None:
                print("waiting for the tests marked idle ...", flush=True)
            results.append(("tests marked idle", computing.wait(), junit["idle"]))
            typed = mypy.wait() if mypy is not None else 0
        finally:
            stopped(computing, group=True)
            stopped(mypy, group=True)
        shown("tests marked idle", idle_log)
        if mypy is not None:
            shown("mypy", typecheck_log)
            results.append(("mypy", typed, None))
    summary(results)
    ran = [code for _, code, report in results if report is not None]  # pytest's, in the order above
    failed = [code for code in ran if code not in (0, NO_TESTS)] + ([typed] if typed else [])
    return failed[0] if failed else (0 if 0 in ran else NO_TESTS)


def runs(
    given: Callable[[str], list[str]], env: dict[str, str], alone: dict[str, str], junit: dict[str, Path]
) -> list[tuple[str, int, Path | None]]:
    """The four pytest runs beside the tests marked idle, as the module's docstring says: each one's title,
    exit status and report."""
    with tempfile.NamedTemporaryFile("w+b", prefix="tether-realtime-", suffix=".log") as log:
        realtime = subprocess.Popen(
            pytest("-m", REALTIME, "-p", "no:cacheprovider", f"--junitxml={junit['realtime']}", *given(REALTIME)),
            stdout=log,
            stderr=log,
            env=alone,
        )
        print(f"tests marked realtime: running alongside at normal priority, output in {log.name}", flush=True)
        try:
            parallel = subprocess.run(
                on_workers("-m", STACKS, f"--junitxml={junit['parallel']}", *given(STACKS), workers=STACK_WORKERS),
                preexec_fn=lambda: os.nice(NICE),
                env=env,
                check=False,
            ).returncode
            if realtime.poll() is None:
                print("waiting for the tests marked realtime ...", flush=True)
            realtime.wait()
        finally:
            stopped(realtime)
        shown("tests marked realtime", log)
    with tempfile.NamedTemporaryFile("w+b", prefix="tether-unit-", suffix=".log") as unit_log:
        unit = None
        try:
            unit = subprocess.Popen(
                on_workers("-m", UNIT, f"--junitxml={junit['unit']}", *given(UNIT)),
                stdout=unit_log,
                stderr=unit_log,
                start_new_session=True,
                preexec_fn=lowest,
                env=env,
            )
            print(
                f"\ntests marked unit: running alongside at the lowest priority, output in {unit_log.name}", flush=True
            )
            print("\n== tests marked alone ==", flush=True)
            by_itself = subprocess.run(
                pytest("-m", ALONE, "-p", "no:cacheprovider", f"--junitxml={junit['alone']}", *given(ALONE)), env=alone
            ).returncode
            units = unit.wait()
        finally:
            stopped(unit, group=True)
        shown("tests marked unit", unit_log)
    return [
        ("tests that start services", parallel, junit["parallel"]),
        ("tests marked realtime", realtime.returncode, junit["realtime"]),
        ("tests marked alone", by_itself, junit["alone"]),
        ("tests marked unit", units, junit["unit"]),
    ]


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
