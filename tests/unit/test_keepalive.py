"""systemd's watchdog is fed only by a loop's rounds that did their work: the robot backend's heartbeat
watch and the simulator's pass. A loop that fails round after round is restarted, not kept alive.
Stand-ins here for the simulation and the watch: the loops' own logic is under test."""

from __future__ import annotations

import threading
from typing import Any, cast

import pytest

from services.ros2.node import Ros2Backend
from services.sim.loop import Report, SimLoop
from services.sim.simulation import Simulation

WAIT = 5.0


class Controllers:
    def stop(self, _reason: str) -> None:
        pass


class FakeSim:
    """Steps time only: what SimLoop.run needs of a Simulation."""

    dt = 0.01
    resting = False

    def __init__(self) -> None:
        self.sim_time = 0.0
        self.controllers = Controllers()

    def step(self, steps: int = 1) -> None:
        self.sim_time += steps * self.dt


class Counted:
    """A keepalive that counts its calls, with the loop's `stop`."""

    def __init__(self) -> None:
        self.feeds = 0
        self.stop = threading.Event()

    def __call__(self) -> None:
        self.feeds += 1


def test_a_sim_pass_whose_report_fails_does_not_feed_the_watchdog_until_it_publishes_again() -> None:
    keepalive = Counted()
    tries: list[bool] = []  # whether each publish of odom went out
    feeds_while_failing: list[int] = []

    def odom(_stamp: float) -> None:
        if len(tries) < 5:
            tries.append(False)
            feeds_while_failing.append(keepalive.feeds)
            raise RuntimeError("the session is closed")
        tries.append(True)
        if keepalive.feeds > 0 or len(tries) > 50:
            keepalive.stop.set()

    loop = SimLoop(cast(Simulation, FakeSim()), 1.0, lambda: None, [Report("odom", 1000.0, odom)])
    worker = threading.Thread(target=loop.run, args=(keepalive.stop, keepalive))
    worker.start()
    worker.join(WAIT)
    keepalive.stop.set()
    worker.join(WAIT)
    assert tries[:6] == [False] * 5 + [True]
    assert set(feeds_while_failing) == {0}, "fed while odom failed to publish"
    assert keepalive.feeds > 0 and not loop.failing, "fed again once odom went out"


def test_a_sim_pass_whose_obey_fails_ends_the_loop_without_feeding() -> None:
    keepalive = Counted()

    def obey() -> str | None:
        raise RuntimeError("the heartbeat guard failed")

    loop = SimLoop(cast(Simulation, FakeSim()), 1.0, obey, [])
    with pytest.raises(RuntimeError, match="guard failed"):
        loop.run(keepalive.stop, keepalive)
    assert keepalive.feeds == 0


class Watch:
    """Stands in for the backend's state that run() reads: its rounds fail while `failing`."""

    def __init__(self, keepalive: Counted, failures: int) -> None:
        self._wake = threading.Event()
        self.keepalive = keepalive
        self.failures = failures
        self.rounds: list[int] = []  # feeds so far at the start of each round

    def _watch(self) -> float:
        self.rounds.append(self.keepalive.feeds)
        if len(self.rounds) <= self.failures:
            raise RuntimeError("the robot could not be told to stop")
        if len(self.rounds) > self.failures + 2:
            self.keepalive.stop.set()
        return 0.0  # due again at once


def test_the_backend_feeds_the_watchdog_only_after_a_watch_round_that_succeeded(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr("services.ros2.node.ESTOP_PERIOD", 0.0)  # a failed round retries at once
    keepalive = Counted()
    watch = Watch(keepalive, failures=4)
    Ros2Backend.run(cast(Any, watch), keepalive.stop, keepalive)
    assert watch.rounds[:5] == [0] * 5, "fed after a failed round"
    assert keepalive.feeds == len(watch.rounds) - 4
