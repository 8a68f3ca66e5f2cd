"""The robot's own stop, pure: emergency_stop latched, a dead-man on its silence, the stop service."""

from __future__ import annotations

from dataclasses import dataclass

ESTOP_REASON = "emergency stop (emergency_stop is true)"
STOP_REASON = "stopped by the stop service"


@dataclass(frozen=True)
class StopState:
    """What the robot must do now."""

    stops: int  # how many stops were asked so far: each ends the running goals once
    stop_reason: str  # why the latest of them was asked
    held: str | None  # why the robot is held still now; None: free to move


class EstopLock:
    """emergency_stop as a robot obeys it, with a twist_mux lock's timeout.

    data=true stops the robot (a counted stop: goals aborted) and holds it until data=false. With
    `timeout` > 0 the topic is also a dead-man signal: once no message has arrived for longer than
    `timeout` the robot stops as on data=true and is held until a message with data=false arrives.
    Before the first message it is held too (a twist_mux lock never heard is locked): a robot whose
    controller never spoke must not move. `timeout` 0 turns the dead-man off (latched value only,
    free to move from the start). Times are monotonic wall seconds, given by the caller. Not
    thread-safe: the caller holds a lock.
    """

    def __init__(self, timeout: float) -> None:
        self.timeout = timeout
        self._active = False  # the latest data
        self._heard_at: float | None = None
        self._silence: str | None = None  # why silence holds the robot; set after a gap over the timeout
        self._stops = 0
        self._stop_reason = ESTOP_REASON

    def heard(self, active: bool, now: float) -> None:
        """A message on emergency_stop, arrived at `now`."""
        self._check_silence(now)  # a gap over the timeout noticed only now still stopped the robot
        if active and not self._active:  # counted, so a true released before the next step still stops
            self._stops, self._stop_reason = self._stops + 1, ESTOP_REASON
        self._active, self._heard_at, self._silence = active, now, None

    def stop_service(self) -> None:
        """The stop service: one stop, not latched."""
        self._stops, self._stop_reason = self._stops + 1, STOP_REASON

    def poll(self, now: float) -> StopState:
        self._check_silence(now)
        return StopState(stops=self._stops, stop_reason=self._stop_reason, held=self._held())

    def _held(self) -> str | None:
        if self.timeout > 0 and self._heard_at is None:
            return f"no emergency_stop signal yet (stop_timeout {self.timeout:g} s)"
        if self._silence is not None:
            return self._silence
        return ESTOP_REASON if self._active else None

    def _check_silence(self, now: float) -> None:
        if self.timeout <= 0 or self._heard_at is None or self._silence is not None:
            return
        quiet = now - self._heard_at
        if quiet > self.timeout:
            self._silence = f"no emergency_stop signal for {quiet:.2f} s (stop_timeout {self.timeout:g} s)"
            self._stops, self._stop_reason = self._stops + 1, self._silence
