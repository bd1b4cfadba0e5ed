"""Discrete filter sections: design in continuous time, discretise once with an explicit dt.

A filter is a cascade of second-order sections (b0, b1, b2, a1, a2) with a0 = 1, run in transposed direct
form II (two state floats per section). Continuous factors (first or second order) are discretised with the
bilinear (Tustin) map prewarped at one frequency: Tustin keeps a stable factor stable and maps the whole
j-axis onto the unit circle without aliasing, and prewarping makes the discrete response exact at the
frequency that matters most (the loop's crossover). python-control does the mapping (`sample_system`).

The same coefficients are run by the compiled laws (controllers/isolation.py, feedforward.py: `sections_step`)
and evaluated by `sos_frf` (analysis).
"""
from __future__ import annotations

import cmath
import math

import numba
import numpy as np

Section = tuple[float, float, float, float, float]     # b0, b1, b2, a1, a2 (a0 = 1)


def tustin_section(num, den, dt: float, prewarp_hz: float | None = None) -> Section:
    """Discretise a continuous factor num(s)/den(s) of order <= 2 with Tustin (prewarped at prewarp_hz).

    s -> k (1 - z^-1) / (1 + z^-1), k = 2/dt, or w_p / tan(w_p dt / 2) prewarped: the same map as
    python-control's sample_system(method="tustin", prewarp_frequency=w_p), written out for one section
    because an optimiser builds thousands of controllers (closed form: ~100x faster)."""
    num = [float(v) for v in np.atleast_1d(num)]
    den = [float(v) for v in np.atleast_1d(den)]
    if len(den) > 3 or len(num) > len(den):
        raise ValueError(f"section must be proper and of order <= 2, got {num}/{den}")
    if prewarp_hz:
        # prewarping beyond Nyquist is meaningless; keep it inside (0, 0.45 fs)
        wp = 2 * math.pi * min(prewarp_hz, 0.45 / dt)
        k = wp / math.tan(wp * dt / 2)
    else:
        k = 2.0 / dt
    n = len(den) - 1                                   # order of the section
    num = [0.0] * (len(den) - len(num)) + num
    if n == 0:
        return (num[0] / den[0], 0.0, 0.0, 0.0, 0.0)

    def mapped(c):                                     # coefficients of z^0, z^-1, z^-2 after the map
        if n == 1:                                     # c1 s + c0, times (1 + z^-1)
            c1, c0 = c
            return (c1 * k + c0, c0 - c1 * k, 0.0)
        c2, c1, c0 = c                                 # c2 s^2 + c1 s + c0, times (1 + z^-1)^2
        kk = k * k
        return (c2 * kk + c1 * k + c0, 2.0 * (c0 - c2 * kk), c2 * kk - c1 * k + c0)
    b, a = mapped(num), mapped(den)
    return (b[0] / a[0], b[1] / a[0], b[2] / a[0], a[1] / a[0], a[2] / a[0])


def sos_frf(sections, w: np.ndarray, dt: float) -> np.ndarray:
    """Frequency response of the cascade at z = exp(j w dt)."""
    zi = np.exp(-1j * np.asarray(w, dtype=float) * dt)      # z^-1
    h = np.ones_like(zi)
    for b0, b1, b2, a1, a2 in sections:
        h = h * (b0 + b1 * zi + b2 * zi * zi) / (1.0 + a1 * zi + a2 * zi * zi)
    return h


def sos_tf(sections, dt: float):
    """The cascade as a python-control discrete TransferFunction (for Nyquist/margins and tests)."""
    import control
    g = control.tf([1.0], [1.0], dt)
    for b0, b1, b2, a1, a2 in sections:
        g = g * control.tf([b0, b1, b2], [1.0, a1, a2], dt)
    return g


@numba.njit(cache=True, inline="always")
def sections_step(st, cf, i, c, count, x):
    """One sample x through `count` sections in series (transposed direct form II): their states from st[i]
    (two each), their coefficients (b0, b1, b2, a1, a2) from cf[c]; returns (output, next i, next c).

    The one cascade step of the compiled laws (controllers/isolation.py, feedforward.py) on flat float arrays:
    inlined into the law, over the law's own state and coefficient arrays (views cost more than the sums)."""
    for _ in range(count):
        yk = cf[c] * x + st[i]
        st[i] = cf[c + 1] * x - cf[c + 3] * yk + st[i + 1]
        st[i + 1] = cf[c + 2] * x - cf[c + 4] * yk
        x = yk
        i += 2
        c += 5
    return x, i, c


def section_dc(sec: Section) -> float:
    b0, b1, b2, a1, a2 = sec
    return (b0 + b1 + b2) / (1.0 + a1 + a2)


def freq_at(sec_list, f_hz: float, dt: float) -> complex:
    """Convenience: the cascade's response at one frequency."""
    zi = cmath.exp(-1j * 2 * math.pi * f_hz * dt)
    h = 1.0 + 0j
    for b0, b1, b2, a1, a2 in sec_list:
        h *= (b0 + b1 * zi + b2 * zi * zi) / (1.0 + a1 * zi + a2 * zi * zi)
    return h


def sos_ss(sections) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """State-space (A, B, C, D) of the cascade with exactly the states the compiled law keeps (transposed direct form
    II, two per section, in the same order): well conditioned even with poles near z = 1, unlike a polynomial."""
    n = 2 * len(sections)
    A = np.zeros((n, n))
    B = np.zeros((n, 1))
    C = np.zeros((1, n))
    D = np.ones((1, 1))
    # running input map: section input x = Cin s + Din u
    Cin = np.zeros((1, n))
    Din = 1.0
    for k, (b0, b1, b2, a1, a2) in enumerate(sections):
        i = 2 * k
        # y = b0 x + s1 ; s1' = b1 x - a1 y + s2 ; s2' = b2 x - a2 y
        ky = (b1 - a1 * b0, b2 - a2 * b0)
        for r, (kx, ka) in enumerate(zip(ky, (a1, a2))):
            A[i + r] += kx * Cin[0]
            A[i + r, i] += -ka
            B[i + r, 0] += kx * Din
        A[i, i + 1] += 1.0
        Cout = b0 * Cin.copy()
        Cout[0, i] += 1.0
        Cin, Din = Cout, b0 * Din
    C[:] = Cin
    D[0, 0] = Din
    return A, B, C, D
