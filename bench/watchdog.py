"""Safety killed to a measured standstill: the sim's heartbeat watchdog stopping the base when safety dies.

    python -m bench.watchdog --json        one JSON object on stdout, progress on stderr
    python -m bench.watchdog               a short table

Measured, in each trial: the base is driven with cmd_vel on `cmd/cmd_vel` (through safety, 20 Hz,
0.3 m/s, forwards and backwards in turn so it stays in the room). Once odometry shows
|linear_x| > 0.1 m/s, t0 = time.time() and the safety process is sent SIGKILL, as a crash would end
it. The halt is the first odometry sample, by the `stamp` the sim puts on it (its wall clock), with
|linear_x| and |angular_z| below 0.01. Nothing tells the sim that safety died: it stops because
safety's heartbeat stops arriving. Safety is then started again, and the next trial waits for its
liveliness token and a heartbeat from it (a restarted safety reads its e-stop state file; this
bench latches nothing, so it resumes, and a latch it did find is reset with the operator token).

The sim and safety are real processes started by the Supervisor on their own robot name and ports;
the sim runs at real time and reports odometry at 500 Hz, so a halt is resolved to about 2 ms. The
figure to compare with is `timeout_ms`, the sim's heartbeat_timeout (from the config this bench
wrote): a halt cannot come before the last beat is that old.
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Any

from bench.service import (
    READY_TIMEOUT,
    Heartbeats,
    RobotMotion,
    Stack,
    bench_main,
    bounded,
    drive,
    halt_trials,
    measured,
    notes,
    print_rows,
    reporter,
    reset_latch,
    robot_ready,
    show,
    wait_until,
)
from services.runtime import load_config
from services.sim.config import SimConfig

PROG = "bench.watchdog"
GOALS = {"goal_ms": 250.0}
SIM = {"realtime_factor": 1.0, "odom_hz": 500.0}
SPEED = 0.3  # m/s
MOVE_TIMEOUT = 10.0  # a restarted safety needs fresh odometry before it passes cmd_vel
HALT_TIMEOUT = 3.0
progress = reporter(PROG)


def trial(stack: Stack, state: RobotMotion, beats: Heartbeats, i: int) -> float:
    """One SIGKILL of safety while the base moves; ms to the halt. Safety is running again after."""
    with drive(stack.node, SPEED if i % 2 == 0 else -SPEED):
        wait_until(state.moving, MOVE_TIMEOUT, "the base moving")
        halt = state.halt_ms(lambda: stack.supervisor.kill("safety"), HALT_TIMEOUT)
    restarted = time.time()
    stack.restart("safety")
    beat = beats.wait(lambda _: True, READY_TIMEOUT, "a heartbeat from the restarted safety", after=restarted)
    if beat.estop.latched:
        progress(f"the restarted safety came back latched ({beat.estop.reason}); resetting it")
        reset_latch(stack, beats)
    return halt


def bench(trials: int) -> dict[str, Any]:
    with robot_ready("watchdog", progress, SIM, arm=False) as (stack, state, beats):
        assert stack.config_file is not None
        timeout = load_config(SimConfig, stack.config_file, "sim").heartbeat_timeout
        halts = halt_trials(trials, lambda i: trial(stack, state, beats, i), progress, "the kill")
    return {
        "halt_ms": round(statistics.median(halts), 2),
        "halt_max_ms": max(halts),
        "halts_ms": halts,
        "timeout_ms": round(timeout * 1000, 3),
        "ratio": round(statistics.median(halts) / (timeout * 1000), 3),
        "trials": len(halts),
        "goals_met": {"halt_max_ms": max(halts) <= GOALS["goal_ms"]},
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    defaults: dict[str, Any] = {
        "halt_ms": None,
        "halt_max_ms": None,
        "halts_ms": [],
        "timeout_ms": None,
        "trials": 0,
        **GOALS,
    }
    result = measured(defaults, lambda: bench(args.trials), progress)
    result["notes"] = notes(
        trial="base on a 20 Hz cmd_vel stream at 0.3 m/s; SIGKILL of safety once odometry shows > 0.1 m/s; "
        "halt at the first odometry sample below 0.01 m/s and rad/s, by the sim's stamp",
        baseline="timeout_ms: the sim's heartbeat_timeout; ratio: halt_ms / timeout_ms",
        sim=SIM,
    )
    return result


def print_table(result: dict[str, Any]) -> None:
    rows = [
        ("halt median ms", show(result["halt_ms"]), ""),
        ("halt max ms", show(result["halt_max_ms"]), f"<= {show(GOALS['goal_ms'])}"),
        ("heartbeat timeout ms (baseline)", show(result["timeout_ms"]), ""),
    ]
    print_rows(f"safety killed to standstill ({result['trials']} trials)", rows, result["errors"])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--trials", type=bounded(int, 1, 100), default=5, help="kills of the safety process")


def main(argv: list[str] | None = None) -> None:
    bench_main(PROG, __doc__ or "", add_arguments, run, print_table, argv)


if __name__ == "__main__":
    main()
