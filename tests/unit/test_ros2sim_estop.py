"""The stand-in's own stop, tick by tick: emergency_stop latched, its silence a dead-man, the stop service."""

from __future__ import annotations

from services.ros2sim.estop import ESTOP_REASON, STOP_REASON, EstopLock, StopState

TIMEOUT = 0.5
PERIOD = 0.05  # the backend's 20 Hz


def heard_until(lock: EstopLock, active: bool, start: float, end: float) -> float:
    """emergency_stop at 20 Hz from `start` to `end`; the time of the last one."""
    now = start
    while now <= end + 1e-9:
        lock.heard(active, now)
        now += PERIOD
    return now - PERIOD


def test_held_before_the_first_message_then_free_on_false() -> None:
    lock = EstopLock(TIMEOUT)
    state = lock.poll(100.0)
    assert state.held is not None and "no emergency_stop signal yet" in state.held
    assert state.stops == 0  # nothing ran, nothing to abort
    assert lock.poll(105.0).stops == 0  # the wait for the first message is not itself a stop
    lock.heard(False, 105.0)
    assert lock.poll(105.0) == StopState(stops=0, stop_reason=ESTOP_REASON, held=None)


def test_a_steady_signal_keeps_it_free() -> None:
    lock = EstopLock(TIMEOUT)
    last = heard_until(lock, False, 0.0, 10.0)
    assert lock.poll(last + TIMEOUT / 2) == StopState(stops=0, stop_reason=ESTOP_REASON, held=None)


def test_silence_over_the_timeout_stops_it_once_and_holds_it() -> None:
    lock = EstopLock(TIMEOUT)
    last = heard_until(lock, False, 0.0, 1.0)
    assert lock.poll(last + TIMEOUT - 0.001).held is None  # not yet
    state = lock.poll(last + TIMEOUT + 0.004)
    assert state.stops == 1 and state.held == state.stop_reason
    assert state.stop_reason == f"no emergency_stop signal for 0.50 s (stop_timeout {TIMEOUT:g} s)"
    later = lock.poll(last + 30.0)
    assert later == state  # one stop, the same reason, still held


def test_it_moves_again_only_when_the_signal_resumes_with_false() -> None:
    lock = EstopLock(TIMEOUT)
    lock.heard(False, 0.0)
    assert lock.poll(1.0).stops == 1
    lock.heard(True, 2.0)
    state = lock.poll(2.0)
    assert state.held == ESTOP_REASON and state.stops == 2
    lock.heard(False, 2.05)
    assert lock.poll(2.05).held is None
    assert lock.poll(2.05).stops == 2


def test_a_gap_noticed_only_at_the_next_message_still_stops_it() -> None:
    lock = EstopLock(TIMEOUT)
    lock.heard(False, 0.0)
    lock.heard(False, 0.8)  # nobody polled in between (a stalled sim thread)
    state = lock.poll(0.8)
    assert state.stops == 1 and "0.80 s" in state.stop_reason
    assert state.held is None  # the signal is back: free once the stop is applied


def test_true_latches_without_repeats_and_counts_each_edge() -> None:
    lock = EstopLock(0.0)  # no dead-man: the latched value only
    assert lock.poll(0.0).held is None  # free from the start
    lock.heard(True, 1.0)
    assert lock.poll(1000.0) == StopState(stops=1, stop_reason=ESTOP_REASON, held=ESTOP_REASON)
    lock.heard(True, 1001.0)
    assert lock.poll(1001.0).stops == 1  # a repeat is no new stop
    lock.heard(False, 1002.0)
    lock.heard(True, 1002.01)
    lock.heard(False, 1002.02)  # set and released before the sim stepped: still a stop
    assert lock.poll(1002.02) == StopState(stops=2, stop_reason=ESTOP_REASON, held=None)


def test_true_holds_while_silent_and_false_after_silence_releases() -> None:
    lock = EstopLock(TIMEOUT)
    lock.heard(True, 0.0)
    state = lock.poll(5.0)
    assert state.stops == 2 and state.held is not None and "no emergency_stop signal" in state.held
    lock.heard(False, 5.0)
    assert lock.poll(5.0).held is None


def test_the_stop_service_stops_once_without_holding() -> None:
    lock = EstopLock(TIMEOUT)
    lock.heard(False, 0.0)
    lock.stop_service()
    assert lock.poll(0.01) == StopState(stops=1, stop_reason=STOP_REASON, held=None)
