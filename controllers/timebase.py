"""The one rule of a timebase: a law discretised for one sample period runs only at that period (its
coefficients are the period's). Two periods within a millionth of each other are the same period (1 / rate in
floating point); the builders' `step` and the period kernel both ask `same_period`."""
from __future__ import annotations

PERIOD_RTOL = 1e-6


def same_period(a_s: float, b_s: float) -> bool:
    """a and b [s] are one sample period (relative to b)."""
    return abs(a_s - b_s) <= PERIOD_RTOL * b_s


def check_step(built_s: float, stepped_s: float, what: str = "controller") -> None:
    """A law built for built_s stepped with stepped_s: ValueError naming both when they differ."""
    if not same_period(stepped_s, built_s):
        raise ValueError(f"{what} built for dt={built_s} s, stepped with dt={stepped_s} s")
