"""The thread that owns a Simulation: physics paced to the wall clock, work from other threads, reports, goals."""

from __future__ import annotations

import functools
import logging
import queue
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

from schemas.actions import GoalState
from schemas.common import ErrorKind, ServiceError
from schemas.world import Empty, FaultReply, GroundTruth, InjectFault, Moved, MoveEntity, MoveReply
from services.actionlib import Outcome
from services.errors import CallError
from services.robotrules import FEEDBACK_PERIOD
from services.sim.controllers import Controllers
from services.sim.simulation import Simulation
from services.sim.world import SETTLE_TIMEOUT, Drop, Motion

log = logging.getLogger(__name__)

T = TypeVar("T")
Command = Callable[[Simulation], None]

START_TIMEOUT = 5.0
ANSWER_TIMEOUT = 2.0
# If the sim falls this far behind the wall clock (sim seconds), it stops trying to catch up.
MAX_LAG = 0.5
# The sim thread looks at the heartbeat at least this often (seconds), even with nothing to step.
MAX_WAIT = 0.05
SHUTTING_DOWN = "the simulator is shutting down"


@dataclass(frozen=True)
class Report:
    """Something the robot publishes on its own schedule, read on the sim thread and stamped with wall time."""

    name: str
    hz: float
    publish: Callable[[float], None]
    # Also while physics catches up with the wall clock: what safety's watchdog must never miss.
    while_catching_up: bool = False


def _woken(command: Command, sim: Simulation) -> None:
    sim.wake()
    command(sim)


class ReportSchedule:
    """When each report is due: on its period, so a late wake-up does not stretch every later one;
    after a stall longer than a period it starts afresh rather than publishing the backlog."""

    def __init__(self, reports: Sequence[Report]) -> None:
        self.reports = list(reports)
        self._due = [0.0] * len(self.reports)  # all due at once at the start

    def due(self, now: float, catching_up: bool = False) -> list[Report]:
        """The reports due at `now` (monotonic seconds), each then scheduled for its next period."""
        due = []
        for i, report in enumerate(self.reports):
            if now < self._due[i] or (catching_up and not report.while_catching_up):
                continue
            period = 1.0 / report.hz
            scheduled = self._due[i] + period
            self._due[i] = scheduled if scheduled > now else now + period
            due.append(report)
        return due

    def next_due(self) -> float:
        """When the next report is due (monotonic seconds); far off when there are none."""
        return min(self._due, default=float("inf"))


class GoalPort(Protocol):
    """What relaying needs of one goal from its action server."""

    @property
    def should_stop(self) -> bool:
        """Asked to stop: canceled, or aborted with `abort_reason`."""
        ...

    @property
    def abort_reason(self) -> str: ...

    def feedback(self, message: Any) -> None: ...


class SimLoop:
    """Owns a Simulation on the thread that calls run(): other threads hand it work through submit().

    `obey` runs on that thread before every step and before a goal starts: it applies whatever
    limits hold now (a heartbeat's, a ROS emergency stop's) and says why the robot must stay
    still, or None.
    """

    def __init__(
        self,
        sim: Simulation,
        realtime_factor: float,
        obey: Callable[[], str | None],
        reports: Sequence[Report] = (),
    ) -> None:
        self.sim = sim
        self.realtime_factor = realtime_factor
        self._obey = obey
        self.schedule = ReportSchedule(reports)
        self._commands: queue.SimpleQueue[Command] = queue.SimpleQueue()
        self._wake = threading.Event()
        # Set (under `_submitting`) as run() ends: no command is taken after its final drain.
        self._submitting = threading.Lock()
        self.ended: str | None = None
        # The goals relay() started, by motion (sim thread only): ended before the next step once asked to stop.
        self._relayed: dict[Motion[Any, Any], GoalPort] = {}
        # The reports whose last publish failed (sim thread only): the watchdog is not fed meanwhile.
        self.failing: set[str] = set()

    # From other threads

    def submit(self, command: Command, changes: bool = True) -> bool:
        """Run `command` on the sim thread. One that may change the world (`changes`, unless it only
        reads) wakes a resting sim first (Simulation.wake). False, and never run, once the thread has
        ended (`ended`)."""
        with self._submitting:
            if self.ended is not None:
                return False
            self._commands.put(functools.partial(_woken, command) if changes else command)
        self._wake.set()
        return True

    def ask(self, query: Callable[[Simulation], T], timeout: float, changes: bool = True) -> T | None:
        """Run `query` on the sim thread and wait for its value; None if the thread does not answer."""
        box: list[T] = []
        answered = threading.Event()

        def run(sim: Simulation) -> None:
            try:
                box.append(query(sim))
            finally:
                answered.set()

        if self.submit(run, changes):
            answered.wait(timeout)
        return box[0] if box else None

    def answer(self, query: Callable[[Simulation], T], changes: bool = True) -> T:
        """`query`'s value from the sim thread, for a queryable: an unavailable error if it does not answer."""
        value = self.ask(query, ANSWER_TIMEOUT, changes)
        if value is None:
            message = f"the simulator did not answer within {ANSWER_TIMEOUT:g} s"
            raise CallError(ServiceError(kind=ErrorKind.UNAVAILABLE, message=message))
        return value

    def ground_truth(self, _request: Empty) -> GroundTruth:
        """sim/ground_truth: every object exactly where it is."""
        return self.answer(lambda sim: sim.scene.ground_truth(), changes=False)

    def change(self, query: Callable[[Simulation], T]) -> T:
        """`answer` for a query that changes the world: one whose caller was told the simulator did
        not answer is not carried out later (it would change the world behind them), and one carried
        out just as the wait ended is answered with what it did."""
        lock = threading.Lock()
        gave_up = False  # set under `lock` once the caller has been told the simulator did not answer
        done: list[T] = []

        def once(sim: Simulation) -> T | None:
            with lock:
                if gave_up:
                    return None
                done.append(query(sim))
                return done[0]

        try:
            value = self.answer(once)  # None only for a caller that has gone
        except CallError:
            with lock:
                gave_up = True
                if not done:
                    raise
                return done[0]
        assert value is not None
        return value

    def move(self, request: MoveEntity) -> MoveReply:
        """sim/move: the reply once the moved thing is at rest, or why it was not moved."""

        def move_now(sim: Simulation) -> Drop | Moved | ServiceError:
            moved = sim.scene.move(request)
            if not isinstance(moved, ServiceError):
                sim.faults.moved(request.id)
            return moved

        moved = self.change(move_now)
        if not isinstance(moved, Drop):
            return moved
        # The object falls and comes to rest while the sim thread keeps stepping (and obeying safety).
        if not moved.done.wait(SETTLE_TIMEOUT / self.realtime_factor + ANSWER_TIMEOUT):
            message = f"{request.id} was moved but the simulator did not report it at rest"
            raise CallError(ServiceError(kind=ErrorKind.TIMEOUT, message=message))
        if moved.state is GoalState.CANCELED:
            raise CallError(ServiceError(kind=ErrorKind.CANCELED, message=moved.message))
        assert moved.result is not None
        return moved.result

    def fault(self, request: InjectFault) -> FaultReply:
        """sim/fault: the fault injected (services/sim/faults.py), or why not."""
        return self.change(lambda sim: sim.faults.inject(request))

    # Goals

    def relay(self, start: Callable[[Controllers], Motion[Any, Any]], goal: GoalPort) -> Outcome[Any]:
        """Carry out one goal, on the calling (action server's) thread: start its motion on the sim
        thread unless `obey` blocks it (or the thread has ended), relay the feedback, and return how
        it ended; the sim thread cancels the motion before its next step once the goal should stop
        (`_enforce`). A goal that should stop before it started never moves."""
        lock = threading.Lock()
        abandoned = False  # set under `lock` when the wait for `begin` gives up
        # What begin did: the motion it started, why it refused, or None when it did not start one
        # because the goal was to stop first.
        started: list[Motion[Any, Any] | str | None] = []
        answered = threading.Event()

        def begin(sim: Simulation) -> None:
            try:
                with lock:
                    if abandoned:
                        return  # its waiter gave up: started now, no cancel could reach it
                    # A motion started once the loop has ended would never be stepped nor end.
                    blocked = self.ended or self._obey()  # as things stand now, not as of the last step
                    if goal.should_stop:
                        started.append(None)
                    elif blocked:
                        started.append(blocked)
                    else:
                        motion = start(sim.controllers)
                        self._relayed[motion] = goal
                        started.append(motion)
            finally:
                answered.set()

        if goal.should_stop:
            return self._ended_before_start(goal)
        if not self.submit(begin):
            return Outcome(GoalState.ABORTED, None, self.ended or "")
        answered.wait(START_TIMEOUT)
        with lock:
            if not started:
                abandoned = True
                return Outcome(GoalState.ABORTED, None, "the simulator did not start the goal")
        motion = started[0]
        if motion is None:
            return self._ended_before_start(goal)
        if isinstance(motion, str):
            return Outcome(GoalState.ABORTED, None, motion)
        # Its cancel is the sim thread's to carry out (_enforce), at once: this thread only relays feedback.
        while not motion.done.wait(FEEDBACK_PERIOD):
            if motion.feedback is not None:
                goal.feedback(motion.feedback)
        return Outcome(motion.state, motion.result, motion.message)

    @staticmethod
    def _ended_before_start(goal: GoalPort) -> Outcome[Any]:
        """A goal canceled (or aborted) before it started: it never moved."""
        if goal.abort_reason:
            return Outcome(GoalState.ABORTED, None, goal.abort_reason)
        return Outcome(GoalState.CANCELED, None, "canceled before it started")

    def _enforce(self) -> None:
        """Before every step: `obey`, then end each relayed goal asked to stop meanwhile, as aborted
        (safety, shutdown) when it has a reason, else as canceled. A cancel that came before a step
        is carried out before it, not once the goal's thread next looked (FEEDBACK_PERIOD later)."""
        self._obey()
        controllers = self.sim.controllers
        for motion, goal in list(self._relayed.items()):
            if motion.running and goal.should_stop:
                if goal.abort_reason:
                    controllers.cancel(motion, GoalState.ABORTED, goal.abort_reason)
                else:
                    controllers.cancel(motion, GoalState.CANCELED, "canceled")
            if not motion.running:
                del self._relayed[motion]

    # The sim thread

    def run(self, stop: threading.Event, keepalive: Callable[[], None] = lambda: None) -> None:
        """Step physics paced to wall time x realtime_factor, publish the reports, obey, until `stop`;
        `keepalive` (systemd's watchdog) after every pass that did its work, so a physics loop that
        hangs, or whose reports fail pass after pass, is restarted. A step or `obey` that raises ends
        the loop (and the service): the robot is not kept within safety's word any more."""
        sim, factor = self.sim, self.realtime_factor
        wall_start, sim_start = time.monotonic(), sim.sim_time
        try:
            while not stop.is_set():
                self._drain()
                self._enforce()
                now = time.monotonic()
                target = sim_start + (now - wall_start) * factor
                if target - sim.sim_time > MAX_LAG:
                    log.warning(
                        "simulation is %.2f s behind the wall clock; dropping the backlog", target - sim.sim_time
                    )
                    wall_start, sim_start = now, sim.sim_time
                    target = sim.sim_time
                while sim.sim_time + sim.dt <= target and not stop.is_set():
                    # At rest (Simulation.step), the ticks due pass at once: nothing but a command
                    # could end the rest, and commands are drained between passes.
                    sim.step(max(1, int((target - sim.sim_time) / sim.dt)) if sim.resting else 1)
                    self._drain()
                    self._enforce()
                    # Also while catching up: on a busy machine physics runs behind, but odometry
                    # and joint states must keep coming, or safety's watchdog sees a silent robot.
                    # Not objects nor people: the perception the robot reports at its own pace.
                    self._publish(catching_up=True)
                self._publish()
                if not self.failing:
                    keepalive()
                wake_at = wall_start + (sim.sim_time + sim.dt - sim_start) / factor
                if sim.resting:  # no tick to take before a report is due or a command comes
                    wake_at = max(wake_at, self.schedule.next_due())
                self._wake.wait(max(0.0, min(wake_at - time.monotonic(), MAX_WAIT)))
                self._wake.clear()
        finally:
            # What was handed over before this runs still runs (a goal's start is refused); nothing after.
            with self._submitting:
                self.ended = SHUTTING_DOWN
            self._drain()
            sim.controllers.stop(SHUTTING_DOWN)

    def _drain(self) -> None:
        while True:
            try:
                command = self._commands.get_nowait()
            except queue.Empty:
                return
            try:
                command(self.sim)
            except Exception:
                log.exception("sim command failed")

    def _publish(self, catching_up: bool = False) -> None:
        """The reports due, each on its own: one that fails (a session closing) is logged when it starts
        and when it ends failing, and holds back the watchdog meanwhile; the others still go out."""
        due = self.schedule.due(time.monotonic(), catching_up)
        stamp = time.time()
        for report in due:
            try:
                report.publish(stamp)
            except Exception:
                if report.name not in self.failing:
                    self.failing.add(report.name)
                    log.exception("%s not published (the watchdog is not fed until it is)", report.name)
                continue
            if report.name in self.failing:
                self.failing.discard(report.name)
                log.info("%s published again", report.name)
