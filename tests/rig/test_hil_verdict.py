"""`rig hil`'s closing verdict (rig/commands/hil.py): a mode that made the table worse, and a host that let more
than 1 % of a mode's periods come late, are each said in one warning line on stderr; a run on time says nothing."""
from __future__ import annotations

from rig.commands.hil import LATE_WARN, _exit_code


def _res(late: dict, fb_db: float = 7.6, ff_db: float = 11.8) -> dict:
    return {"isolation_reduction_db": fb_db, "feedforward_reduction_db": ff_db, "faults": 0, "harm": None,
            "late_periods": late}


def test_a_run_on_time_says_nothing(capsys):
    assert _exit_code(_res({"off": 0.001, "feedback": 0.002, "feedback_feedforward": None})) == 0
    assert capsys.readouterr().err == ""


def test_late_periods_beyond_the_bound_are_said_in_one_line(capsys):
    assert _exit_code(_res({"off": 0.383, "feedback": 0.002, "feedback_feedforward": LATE_WARN * 1.5})) == 0
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "the host did not keep time" in lines[0]
    assert "off 38.3 %" in lines[0] and "feedback + feedforward 1.5 %" in lines[0]
    assert "feedback 0.2" not in lines[0]


def test_a_mode_worse_than_off_is_said(capsys):
    assert _exit_code(_res({"off": 0.0}, fb_db=-4.0)) == 0
    assert "feedback made the table 4.0 dB worse than isolation off" in capsys.readouterr().err
