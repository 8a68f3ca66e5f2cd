"""An e-stop asked for while the latch already holds, in safety's gate on a fake clock: the latch stays
as the first one set it, and the request is an event naming who asked and why (repeats from one source
counted, as repeated vetoes are), which is no new incident; a reset's event names the operator."""

from __future__ import annotations

from schemas import keys
from schemas.safety import Decision, EStop, EstopSource, ResetRequest, Rule
from services.safety.gate import REPEAT_WINDOW, GateEvent, SafetyGate
from services.safety.incidents import IncidentWatch
from tests.unit.test_safety_gate import TOKEN, FakeClock, clock, gate, joints, wall_clock
from tests.unit.test_safety_gate import policy as policy  # the module-scoped fixture, shared

__all__ = ["clock", "gate", "policy", "wall_clock"]  # fixtures


def test_an_estop_asked_for_while_latched_is_an_event_naming_who_and_why(gate: SafetyGate, clock: FakeClock) -> None:
    assert gate.estop(EStop(source=EstopSource.AGENT, reason="looping")).latched
    clock.advance(5.0)
    again = gate.estop(EStop(source=EstopSource.OPERATOR, reason="person on the floor"))
    assert not again.latched, "asked again, it does not latch anew (no second stop, state write or cancel)"
    (event,) = again.events
    assert (event.key, event.decision, event.rule) == (keys.ESTOP.path, Decision.LATCHED, Rule.ESTOP)
    assert event.reason.startswith("by operator: person on the floor")
    assert "already latched by agent: looping" in event.reason
    assert event.values["already_latched"] == 1.0
    assert event.command == EStop(source=EstopSource.OPERATOR, reason="person on the floor")
    # The latch is as the first one set it.
    state = gate.latch.state
    assert (state.latched, state.source, state.reason) == (True, "agent", "looping")


def test_a_trip_while_latched_is_an_event_too(gate: SafetyGate, clock: FakeClock) -> None:
    assert gate.estop(EStop(source=EstopSource.OPERATOR, reason="stop")).latched
    gate.joint_state(joints(0.5))
    clock.advance(1.0)  # the arm was last seen moving, then nothing
    tick = gate.tick()
    (event,) = [e for e in tick.events if e.key == keys.ESTOP.path]
    assert not tick.latched and event.rule is Rule.WATCHDOG and "no joint states" in event.reason
    assert "already latched by operator: stop" in event.reason and event.values["already_latched"] == 1.0


def test_repeats_from_one_source_are_counted_while_another_source_always_gets_its_own_event(
    gate: SafetyGate, clock: FakeClock
) -> None:
    gate.estop(EStop(source=EstopSource.AGENT, reason="first"))
    events: list[GateEvent] = []
    for i in range(20):
        clock.advance(0.01)
        events += gate.estop(EStop(source=EstopSource.AGENT, reason=f"again {i}")).events
        if i == 10:
            events += gate.estop(EStop(source=EstopSource.OPERATOR, reason="me too")).events
    assert [e.reason.split(";")[0] for e in events] == ["by agent: again 0", "by operator: me too"]
    clock.advance(REPEAT_WINDOW)
    (counted,) = [e for e in gate.tick().events if e.key == keys.ESTOP.path]
    assert counted.decision is Decision.LATCHED and counted.values["count"] == 19.0
    assert counted.values["already_latched"] == 1.0
    assert "19 more asked for by agent" in counted.reason and "by agent: again 19" in counted.reason


def test_an_estop_asked_for_while_latched_is_no_new_incident(gate: SafetyGate) -> None:
    watch = IncidentWatch(near_miss_distance=0.5)
    first = gate.estop(EStop(source=EstopSource.AGENT, reason="looping"))
    assert len(watch.decided(first.events, gate.latch.state)) == 1
    again = gate.estop(EStop(source=EstopSource.OPERATOR, reason="me too"))
    assert again.events and watch.decided(again.events, gate.latch.state) == []


def test_a_reset_and_a_refused_one_name_the_operator(gate: SafetyGate) -> None:
    gate.estop(EStop(source=EstopSource.AGENT, reason="stop"))
    wrong = gate.reset(ResetRequest(operator="mallory", token="guess"))
    assert "'mallory'" in wrong.events[0].reason
    right = gate.reset(ResetRequest(operator="alice", token=TOKEN))
    assert right.events[0].reason == "by operator alice" and gate.latch.state.source == "alice"
