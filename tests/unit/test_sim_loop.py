"""The sim thread's report schedule, tick by tick: on its period, never a backlog, only the vital ones while behind."""

from __future__ import annotations

from services.sim.loop import Report, ReportSchedule


def schedule() -> ReportSchedule:
    return ReportSchedule(
        [Report("odom", 50.0, lambda _t: None, while_catching_up=True), Report("objects", 5.0, lambda _t: None)]
    )


def names(reports: list[Report]) -> list[str]:
    return [r.name for r in reports]


def test_every_report_is_due_at_once_then_on_its_period() -> None:
    s = schedule()
    assert names(s.due(100.0)) == ["odom", "objects"]
    assert names(s.due(100.01)) == []
    assert names(s.due(100.021)) == ["odom"]
    assert names(s.due(100.201)) == ["odom", "objects"]


def test_a_late_wake_up_does_not_stretch_the_next_period() -> None:
    s = schedule()
    s.due(100.0)
    assert names(s.due(100.03)) == ["odom"]  # 10 ms late
    assert names(s.due(100.041)) == ["odom"]  # due again at 100.04, not 100.05


def test_after_a_stall_it_starts_afresh_without_a_backlog() -> None:
    s = schedule()
    s.due(100.0)
    assert names(s.due(101.0)) == ["odom", "objects"]
    assert names(s.due(101.01)) == []
    assert names(s.due(101.021)) == ["odom"]


def test_while_catching_up_only_the_reports_safety_watches_go_out() -> None:
    s = schedule()
    assert names(s.due(100.0, catching_up=True)) == ["odom"]
    assert names(s.due(100.0)) == ["objects"]
