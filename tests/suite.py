"""`make test`'s pytest run, sized for a 2-core machine: `python -m tests.suite [--typecheck] [PYTEST ARGS]`.

First, two pytest runs at once:
- the tests marked `realtime` (they bound halts, report rates and watchdogs in wall seconds), one at a
  time at normal priority; their output goes to a file and is shown when they end;
- everything else on two pytest-xdist workers (`--dist loadscope`: whole modules, so a module's
  shared stack stays on one worker, in the order tests/conftest.py explains), at low priority
  (nice 15), its output on the terminal.
Then the tests marked `alone` (realtime too: the multi-host tests, two robots' stacks in network
namespaces with a router and link proxies, the ROS 2 stand-in's, whose dead-man signal comes from
the test process at 20 Hz, and the robot contract's, whose safety heartbeat a child process plays,
tests/robot_contract/played_safety.py) one at a time, without the rest: with the others' load
beside them, their robots' heartbeats or signals came late now and then. That held for these
modules beside each other too (two workers: the multi-host module on one, the stand-in's and the
contract's on the other). With the contract's heartbeat a thread of the test process, each of six
such runs on 2026-11-27 lost a contract test to a late heartbeat. Played by a child process, five
of six runs passed (about 140 s each) and one lost a contract test the same way: the robot saw no
heartbeat for 200 ms. One at a time they take about two and a half minutes (the multi-host sims at four
times real time) and use about half a core.
With --typecheck, mypy runs beside them on the core they leave, under SCHED_IDLE (it gets only
what nothing else wants: about 17 s of CPU, off the suite's critical path), its output shown after
theirs.

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
The exit status is the first failing run's (pytest's codes, then mypy's), or 0.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

# Low priority for the parallel part: at nice 15 a process weighs 1/28 of one at nice 0.
NICE = 15
# pytest's exit status when a selection holds no test: a run of files without such tests is fine.
NO_TESTS = 5
# Set, Python and pytest write no bytecode, so pytest's assertion rewriting is not kept.
WRITE_NO_BYTECODE = "PYTHONDONTWRITEBYTECODE"
# `make typecheck`'s check (its settings in pyproject.toml).
MYPY = [sys.executable, "-m", "mypy"]


def pytest(*args: str) -> list[str]:
    """pytest, quiet, listing each run's 15 slowest tests at the end (the suite's time is watched)."""
    return [sys.executable, "-m", "pytest", "-q", "--durations=15", *args]


def idle() -> None:
    """In a child before exec: run only on CPU nothing else wants."""
    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))


def main(argv: list[str]) -> int:
    typecheck = argv[:1] == ["--typecheck"]
    extra = argv[1:] if typecheck else argv
    extra = extra or ["tests"]
    # Three bands of ports (tests/sessions.py): one per worker, the last for the realtime runs.
    # pytest keeps each test module as it rewrote its asserts in __pycache__ (beside Python's own
    # bytecode, which compileall writes; pytest's is its own), unless bytecode is not to be written
    # (PYTHONDONTWRITEBYTECODE, set on this machine): then every pytest process rewrites every
    # module again, and collecting the suite took 13 s of CPU instead of 6. The first pytest
    # processes of a fresh clone write it; those after them, and every later `make test`, reuse it.
    env = {name: value for name, value in os.environ.items() if name != WRITE_NO_BYTECODE}
    env |= {"TETHER_TEST_PORT_BANDS": "3"}
    alone = env | {"TETHER_TEST_PORT_BAND": "2"}
    with tempfile.NamedTemporaryFile("w+b", prefix="tether-realtime-", suffix=".log") as log:
        realtime = subprocess.Popen(
            pytest("-m", "realtime and not alone", "-p", "no:cacheprovider", *extra),
            stdout=log,
            stderr=log,
            env=alone,
        )
        print(f"tests marked realtime: running alongside at normal priority, output in {log.name}", flush=True)
        try:
            parallel = subprocess.run(
                pytest("-n", "2", "--dist", "loadscope", "-m", "not realtime", *extra),
                preexec_fn=lambda: os.nice(NICE),
                env=env,
                check=False,
            ).returncode
            if realtime.poll() is None:
                print("waiting for the tests marked realtime ...", flush=True)
            realtime.wait()
        finally:
            if realtime.poll() is None:
                realtime.terminate()
                realtime.wait()
        print("\n== tests marked realtime ==", flush=True)
        sys.stdout.buffer.write(Path(log.name).read_bytes())
        sys.stdout.flush()
    print("\n== tests marked alone ==", flush=True)
    with tempfile.TemporaryFile("w+b") as typecheck_log:
        mypy = None
        if typecheck:
            mypy = subprocess.Popen(MYPY, stdout=typecheck_log, stderr=typecheck_log, preexec_fn=idle)
        try:
            by_itself = subprocess.run(pytest("-m", "alone", "-p", "no:cacheprovider", *extra), env=alone).returncode
            typed = mypy.wait() if mypy is not None else 0
        finally:
            if mypy is not None and mypy.poll() is None:
                mypy.kill()
                mypy.wait()
        if mypy is not None:
            print("\n== mypy ==", flush=True)
            typecheck_log.seek(0)
            sys.stdout.buffer.write(typecheck_log.read())
            sys.stdout.flush()
    runs = (parallel, realtime.returncode, by_itself)
    failed = [code for code in runs if code not in (0, NO_TESTS)] + ([typed] if typed else [])
    return failed[0] if failed else (0 if 0 in runs else NO_TESTS)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
