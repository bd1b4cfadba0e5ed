"""The output limits inside the control laws (compiled): a clamp and a slew limit that also report the side
they limited on (sat = +1 / -1, else unchanged), for the laws' conditional-integration anti-windup."""
from __future__ import annotations

import numba


@numba.njit(cache=True, inline="always")
def clamp(u, lim, sat):
    if u > lim:
        return lim, 1.0
    if u < -lim:
        return -lim, -1.0
    return u, sat


@numba.njit(cache=True, inline="always")
def slew(u, up, step, sat):
    """At most `step` away from the previous output up."""
    if u - up > step:
        return up + step, 1.0
    if up - u > step:
        return up - step, -1.0
    return u, sat
