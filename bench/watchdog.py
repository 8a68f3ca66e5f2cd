"""Safety killed to a measured standstill: the robot's heartbeat watchdog stopping the base when safety dies.

    python -m bench.watchdog --json                  one JSON object on stdout, progress on stderr
    python -m bench.watchdog                         a short table
    python -m bench.watchdog --backend ros2 --json   the same, with the ros2 backend and the stand-in robot

Measured, in each trial: the base is driven with cmd_vel on `cmd/cmd_vel` (through safety, 20 Hz,
0.3 m/s, forwards and backwards in turn so it stays in the room). Once odometry shows
|linear_x| > 0.1 m/s, t0 = time.time() and the safety process is sent SIGKILL, as a crash would end
it. The halt is the first odometry sample, by the `stamp` the sim puts on it (its wall clock), with
|linear_x| and |angular_z| below 0.01. Nothing tells the sim that safety died: it stops because
safety's heartbeat stops arriving. Safety is then started again, and the next trial waits for its
liveliness token and a heartbeat from it (a restarted safety reads its e-stop state file; this
bench latches nothing, so it resumes, and a latch it did find is reset with the operator token).

The sim and safety are real processes started by the Supervisor on their own robot name and ports;
the sim runs at real time and is asked for odometry at 500 Hz, but reports at most once a physics
step (240 Hz), so a halt is resolved to about 4 ms. The figure to compare with is `timeout_ms`, the
sim's heartbeat_timeout (from the config this bench wrote): a halt cannot come before the last beat
is that old.

With `--backend ros2` (default `sim`; the JSON's `backend` says which ran), the ros2 backend and the
stand-in ROS 2 robot (ros2sim: the same sim, as configured above, behind a ROS 2 face on rmw_zenoh
keys, on a loopback Zenoh network of their own) run in the sim's place. The stand-in knows nothing of
safety: the backend's heartbeat watch stops it, publishing `emergency_stop` true and a zero cmd_vel
once the last beat is `[ros2] heartbeat_timeout` old, and that is `timeout_ms`. The halt is measured
in the same way, on odometry as the backend publishes it on tether's side, by the stand-in's stamps;
the backend's rate limit (`[ros2] odom_hz`) is raised to 1 kHz so it passes all of them on. Unlike
the sim, the stand-in also renders its camera picture (`[ros2sim] camera_hz`, 1 Hz) on its sim
thread, and neither reports nor hears anything while it does. The goal is the same.
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
    add_backend_argument,
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
from services.ros2.config import Ros2Config
from services.runtime import load_config
from services.sim.config import SimConfig

PROG = "bench.watchdog"
GOALS = {"goal_ms": 250.0}
SIM = {"realtime_factor": 1.0, "odom_hz": 500.0}
# With --backend ros2: the backend's rate limit above the stand-in's rate, so it passes every report on.
ROS2 = {"odom_hz": 1000.0}
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


def heartbeat_timeout(stack: Stack, backend: str) -> float:
    """The heartbeat_timeout of the service that watches the heartbeat, from the config this bench wrote."""
    assert stack.config_file is not None
    if backend == "ros2":
        return load_config(Ros2Config, stack.config_file, "ros2").heartbeat_timeout
    return load_config(SimConfig, stack.config_file, "sim").heartbeat_timeout


def bench(trials: int, backend: str) -> dict[str, Any]:
    with robot_ready("watchdog", progress, SIM, arm=False, backend=backend, ros2=ROS2) as (stack, state, beats):
        timeout = heartbeat_timeout(stack, backend)
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
        "backend": args.backend,
        "halt_ms": None,
        "halt_max_ms": None,
        "halts_ms": [],
        "timeout_ms": None,
        "trials": 0,
        **GOALS,
    }
    result = measured(defaults, lambda: bench(args.trials, args.backend), progress)
    result["notes"] = notes(
        trial="base on a 20 Hz cmd_vel stream at 0.3 m/s; SIGKILL of safety once odometry shows > 0.1 m/s; "
        "halt at the first odometry sample below 0.01 m/s and rad/s, by the robot's stamp",
        baseline=f"timeout_ms: the {args.backend} backend's heartbeat_timeout; ratio: halt_ms / timeout_ms",
        sim=SIM,
        **({"ros2": ROS2} if args.backend == "ros2" else {}),
    )
    return result


def print_table(result: dict[str, Any]) -> None:
    rows = [
        ("halt median ms", show(result["halt_ms"]), ""),
        ("halt max ms", show(result["halt_max_ms"]), f"<= {show(GOALS['goal_ms'])}"),
        ("heartbeat timeout ms (baseline)", show(result["timeout_ms"]), ""),
    ]
    title = f"safety killed to standstill, {result['backend']} ({result['trials']} trials)"
    print_rows(title, rows, result["errors"])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--trials", type=bounded(int, 1, 100), default=5, help="kills of the safety process")
    add_backend_argument(parser)


def main(argv: list[str] | None = None) -> None:
    bench_main(PROG, __doc__ or "", add_arguments, run, print_table, argv)


if __name__ == "__main__":
    main()
