"""The diagnosis's wording where a newcomer read a contradiction (issue 29): the augmented fit's bands beside a
verdict that the model explains the recording are not "still off"."""
from __future__ import annotations

from rig.diagnose.report import _mismatch_rows
from rig.diagnose.results import Mismatch, Verdict


def _mismatch(after_bands):
    return Mismatch(uncorrelated={}, command={}, bands_hz=[(2.0, 3.0)], windows_s=[], after_refit={"bands_hz": []},
                    after_augmented={"bands_hz": after_bands}, regimes={}, worst_windows={}, chirp_band_hz=[],
                    notes=())


def _after(rows):
    return next((long, text) for short, long, text in rows if short == "after augmented")


def test_explained_does_not_stand_beside_bands_still_off():
    long, text = _after(_mismatch_rows(_mismatch([(40.0, 45.0)]), 6, Verdict("explained", 1.02, 3.0, True)))
    assert "still off" not in long and "40-45 Hz" in text and "at the noise, 1.02x" in text


def test_a_verdict_short_of_explained_keeps_them_off():
    for status in ("partly", "incomplete", "not_described"):
        long, text = _after(_mismatch_rows(_mismatch([(40.0, 45.0)]), 6, Verdict(status, 2.0, 3.0, True)))
        assert long == "Bands still off after the augmented fit" and text == "40-45 Hz"
    long, text = _after(_mismatch_rows(_mismatch([]), 6, Verdict("explained", 1.0, 3.0, True)))
    assert text == "none"


def test_an_interval_reads_with_its_estimate_decimals():
    from rig.diagnose.report import format_parameters
    text = format_parameters({"force_n": 402.1}, {"force_n": (395.0, 408.5)})
    assert text == "force 402.1 N (95 %: 395.0 to 408.5)"
    assert format_parameters({"x": 1.632e5}, {"x": (1.2e5, 2.0e5)}) == "x 1.632e+05 (95 %: 1.2e+05 to 2e+05)"
