"""What a friction model costs the axis diagnosis (issue 26, speed): the friction solve returns a sliding root
without bisecting to it."""
import math

import numpy as np

from rig.plant.zoh import friction_velocity


def test_a_sliding_root_is_the_slip_solution_itself():
    """Sliding, tanh(v / v_s) is 1.0 in double precision: the root is the slip solution (c0 - F_c) / c1, exactly.
    Before, Newton's step landed on that edge of its bracket, was refused, and the solve bisected towards it in
    ~20 steps a sub-step, stopping within its tolerance (1e-9 of v) instead."""
    vs = 1e-7
    for c0, c1, fric in ((3e-3, 1.0, 4e-5), (-2e-2, 1.0, 1e-4), (0.5, 3.0, 0.2), (1e-4, 1.0, 9.7e-5)):
        v = friction_velocity(c0, c1, fric, vs, 0.0, 1e-13, 1e-9)
        assert v == (c0 - math.copysign(fric, c0)) / c1, (c0, v)
        assert abs(c0 - c1 * v - fric * math.tanh(v / vs)) <= 4 * abs(np.spacing(c0)), (c0, v)


def test_a_sliding_root_with_stribeck_is_found_to_the_tolerance():
    """With a Stribeck breakaway the sliding equation stays smooth where tanh is saturated: Newton on it from the
    slip solution, not the bracketed search."""
    vs, vst = 1e-7, 1e-2
    for c0, fric, sx in ((3e-3, 4e-5, 3e-5), (-5e-4, 4e-5, 6e-5), (2e-4, 1e-4, 9e-5)):
        v = friction_velocity(c0, 1.0, fric, vs, 0.0, 1e-13, 1e-9, sx, vst)
        s = math.copysign(1.0, c0)
        residual = c0 - v - s * (fric + sx * math.exp(-(v / vst) ** 2))
        assert s * v > 20 * vs and abs(residual) < 1e-15, (c0, v, residual)
