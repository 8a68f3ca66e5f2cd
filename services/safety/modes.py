"""The control mode (held durably) and the book of plans waiting for, or running on, an operator's approval."""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, replace
from pathlib import Path

import msgspec

from schemas.common import TEXT_CHARS
from schemas.plan import GroundedPlan, fallback_labels, step_labels
from schemas.safety import MAX_PLAN_LINES, ApprovalState, ControlMode, ModeState, PlanApproval
from services.datafile import read_bytes
from services.safety.latch import write_durably

log = logging.getLogger(__name__)

# What each mode says to a plan, or to a program's motion, it refuses (None: the mode lets plans run).
PLANS_REFUSED = {
    ControlMode.DIRECT: "mode direct: only the operator drives (teleop); plans are refused",
    ControlMode.SHARED: "mode shared: the operator drives (teleop); plans are refused",
}
# Plans waiting longer than this for an operator are denied (the world has changed since they were checked).
APPROVAL_EXPIRY = 900.0
# Plans remembered after they ended or were denied (an approve of one gets a clear answer), and for how long.
ENDED_KEPT = 256
ENDED_FOR = 1800.0
# At most this many plans wait at once; more are denied at once.
MAX_WAITING = 32


class ModeFile:
    """The mode, written down on every change and read back at start. No file: autonomous, the
    default (a fresh install, or `tether deploy init`, has none). A file that cannot be read:
    supervised, so that nothing moves without a person while nobody knows what was chosen."""

    def __init__(self, path: Path | None) -> None:
        self._file = path
        self._lock = threading.Lock()
        # One save at a time, each writing the state current when its turn comes (as EstopLatch.save):
        # two at once shared the temporary file, and an older state could be renamed in over a newer.
        self._file_lock = threading.Lock()
        self._state = self._load()

    def _load(self) -> ModeState:
        if self._file is None or not self._file.exists():
            return ModeState(mode=ControlMode.AUTONOMOUS, source="default")
        try:
            # Bounded and not blocking, as the e-stop state file.
            state = msgspec.json.decode(read_bytes(self._file, "mode state", OSError), type=ModeState)
        except (OSError, msgspec.DecodeError) as exc:
            log.error("mode state file %s is unreadable (%s): starting supervised", self._file, exc)
            return ModeState(mode=ControlMode.SUPERVISED, source=f"safety: unreadable mode state file {self._file}")
        log.info("control mode %s (set by %s)", state.mode, state.source or "unknown")
        return state

    @property
    def state(self) -> ModeState:
        with self._lock:
            return self._state

    @property
    def mode(self) -> ControlMode:
        return self.state.mode

    def set(self, mode: ControlMode, source: str, stamp: float) -> ModeState:
        """Change it in memory; the previous state is returned. save() writes it down."""
        with self._lock:
            previous, self._state = self._state, ModeState(mode=mode, source=source, stamp=stamp)
            return previous

    def save(self) -> None:
        """Write the current state down (the latest wins when several write at once)."""
        if self._file is None:
            return
        with self._file_lock:
            write_durably(self._file, msgspec.json.encode(self.state))


def plan_lines(plan: GroundedPlan) -> list[str]:
    """The plan's steps and route, one line each, as an operator reads them before approving."""
    labels = step_labels(plan)
    lines = [f"{label}. {step.brief()}" for label, step in zip(labels, plan.steps, strict=True)]
    for fallback in plan.fallbacks:
        alternative = fallback_labels(fallback, labels)
        lines += [f"{label}. {step.brief()}" for label, step in zip(alternative, fallback.steps, strict=True)]
    if len(lines) > MAX_PLAN_LINES:
        lines = [*lines[: MAX_PLAN_LINES - 1], f"... and {len(lines) - MAX_PLAN_LINES + 1} more"]
    return [line[:TEXT_CHARS] for line in lines]


@dataclass(frozen=True)
class _Entry:
    approval: PlanApproval
    plan: GroundedPlan
    at: float  # the gate's clock, when it was asked or last changed
    by_mode: bool = False  # approved because the mode needed no approval, not by an operator


class ApprovalBook:
    """Plans of supervised mode by goal id: pending until an operator decides, approved (or paused
    by an operator meanwhile) until the executor reports the goal ended, then remembered a while as
    finished (or denied). Not thread-safe: the gate calls it under its lock."""

    def __init__(self) -> None:
        self._entries: dict[str, _Entry] = {}
        # Goals reported ended before they were asked about, and why (the last ENDED_KEPT).
        self._gone: dict[str, str] = {}

    def get(self, goal_id: str, t: float) -> PlanApproval | None:
        self._expire(t)
        entry = self._entries.get(goal_id)
        return None if entry is None else entry.approval

    def plan(self, goal_id: str) -> GroundedPlan | None:
        entry = self._entries.get(goal_id)
        return None if entry is None else entry.plan

    def waiting(self, t: float) -> list[PlanApproval]:
        self._expire(t)
        pending = [e for e in self._entries.values() if e.approval.state is ApprovalState.PENDING]
        return [e.approval for e in sorted(pending, key=lambda e: e.approval.requested)]

    def count(self, state: ApprovalState) -> int:
        return sum(1 for e in self._entries.values() if e.approval.state is state)

    def add(self, approval: PlanApproval, plan: GroundedPlan, t: float) -> PlanApproval:
        """Hold a plan not held yet (the caller looks first, under the same lock)."""
        self._expire(t)
        gone = self._gone.pop(approval.goal_id, None)
        if approval.state is ApprovalState.PENDING and gone is not None:
            # Its executor gave up on it (an ask that took too long) before it was held here: kept
            # waiting, an operator could approve a plan no one runs, whose end would never come.
            approval = replace_approval(approval, ApprovalState.DENIED, gone)
        elif approval.state is ApprovalState.PENDING and self.count(ApprovalState.PENDING) >= MAX_WAITING:
            approval = replace_approval(
                approval, ApprovalState.DENIED, f"{MAX_WAITING} plans already wait for an operator: decide those first"
            )
        self._entries[approval.goal_id] = _Entry(approval, plan, t)
        return approval

    def gone(self, goal_id: str, reason: str) -> None:
        """`goal_id` was reported ended while not held: an ask for it still on its way is denied for `reason`."""
        self._gone[goal_id] = reason[:TEXT_CHARS]
        for old in list(self._gone)[: max(0, len(self._gone) - ENDED_KEPT)]:
            del self._gone[old]

    def change(self, goal_id: str, state: ApprovalState, reason: str, t: float, **fields: object) -> PlanApproval:
        entry = self._entries[goal_id]
        approval = replace_approval(entry.approval, state, reason, **fields)
        self._entries[goal_id] = replace(entry, approval=approval, at=t, by_mode=False)
        return approval

    def let_run(self, goal_id: str, reason: str, t: float, decided: float) -> PlanApproval:
        """Approved because the mode needs no approval (autonomous), not by an operator."""
        approval = self.change(goal_id, ApprovalState.APPROVED, reason, t, decided=decided, by="mode")
        self._entries[goal_id] = replace(self._entries[goal_id], by_mode=True)
        return approval

    def deny_unreviewed(self, reason: str, t: float) -> list[PlanApproval]:
        """Supervised mode again: every plan approved only because the mode needed no approval is
        denied for `reason` (an operator never approved it). The approvals as they now are."""
        unreviewed = [g for g, e in self._entries.items() if e.by_mode and e.approval.state is ApprovalState.APPROVED]
        return [self.change(goal_id, ApprovalState.DENIED, reason, t) for goal_id in unreviewed]

    def end_all(self, reason: str, t: float) -> list[PlanApproval]:
        """Every plan waiting (denied), approved or paused (finished) ends for `reason`: their
        executor is gone, and none of them will be reported ended. The approvals as they now are."""
        ended = []
        for goal_id, entry in list(self._entries.items()):
            state = entry.approval.state
            if state is ApprovalState.PENDING:
                ended.append(self.change(goal_id, ApprovalState.DENIED, reason, t))
            elif state in (ApprovalState.APPROVED, ApprovalState.PAUSED):
                ended.append(self.change(goal_id, ApprovalState.FINISHED, reason, t))
        return ended

    def running(self) -> str | None:
        """The goal id of an approved plan (which may move the robot), if any."""
        return next((g for g, e in self._entries.items() if e.approval.state is ApprovalState.APPROVED), None)

    def paused(self) -> list[PlanApproval]:
        """The plans an operator paused while they ran (their motion refused until resumed)."""
        return [e.approval for e in self._entries.values() if e.approval.state is ApprovalState.PAUSED]

    def _expire(self, t: float) -> None:
        for goal_id, entry in list(self._entries.items()):
            state = entry.approval.state
            if state is ApprovalState.PENDING and t - entry.at > APPROVAL_EXPIRY:
                why = f"no operator decided within {APPROVAL_EXPIRY / 60:g} minutes"
                self.change(goal_id, ApprovalState.DENIED, why, t)
            elif state in (ApprovalState.DENIED, ApprovalState.FINISHED) and t - entry.at > ENDED_FOR:
                del self._entries[goal_id]
        done = (ApprovalState.DENIED, ApprovalState.FINISHED)
        ended = [g for g, e in self._entries.items() if e.approval.state in done]
        for goal_id in ended[: max(0, len(ended) - ENDED_KEPT)]:
            del self._entries[goal_id]


def replace_approval(approval: PlanApproval, state: ApprovalState, reason: str, **fields: object) -> PlanApproval:
    return msgspec.structs.replace(approval, state=state, reason=reason[:TEXT_CHARS], **fields)
