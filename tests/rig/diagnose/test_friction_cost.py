"""What a friction model costs the axis diagnosis (issue 26, speed): the friction solve returns a sliding root
without bisecting to it, and a fit's Jacobian columns are one simulation each, from the segment states refined at
the point the fit stands on."""
import math
import threading

import numpy as np

from rig.diagnose import problem
from rig.excitation import band_noise
from rig.plant.file import parse_plant
from rig.plant.zoh import friction_velocity
from sim_backend.axis import Axis, Sensor, simulate_axis

PLANT = {"family": "mechanical_axis", "input_unit": "N", "mass_kg": {"value": 25.0, "min": 5.0, "max": 100.0},
         "damping_n_s_per_m": {"value": 50.0, "min": 5.0, "max": 500.0}}
NOISE_M = 2e-7
FRICTION_N = 4.0


def _friction_problem() -> problem.Problem:
    """12 s of an open-loop axis of 20 kg with 4 N of Coulomb friction under a 40 N band-noise force."""
    ax = Axis(mass_kg=20.0, damping_n_s_per_m=60.0, gain_n_per_unit=1.0, coulomb_n=FRICTION_N)
    u = band_noise(1000.0, 12.0, 0.3, 30.0, 40.0, seed=5).cmd_V
    cmd, pos = simulate_axis(ax, 1000.0, command=u, sensor=Sensor(noise_m=NOISE_M, offset_m=3e-4, seed=2))
    pb = problem.Problem(cmd, pos, 1000.0, parse_plant(PLANT, "axis.toml"), np.ones(len(pos), bool), noise=NOISE_M)
    assert pb.shoot is not None
    return pb


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


def test_a_friction_fits_columns_are_one_simulation_each():
    """The Jacobian's columns start from the segment states refined at the point the fit stands on and are not
    refined again: one friction simulation each. Before, each column refined its states from the data's, two or
    three simulations (rig prove --plant emps_axis.toml seed 1, a03: 1284 friction simulations, now 893)."""
    pb = _friction_problem()
    in_column = threading.local()
    column_runs, other_runs, columns = [], [], []
    simulate = pb.plant.simulate

    def counted(*a, **k):
        (column_runs if getattr(in_column, "on", False) else other_runs).append(1)
        return simulate(*a, **k)
    pb.plant.simulate = counted
    lm_fit = problem.lm_fit

    def lm(fun, *a, near=None, **k):
        def column(xp, x):
            in_column.on = True
            columns.append(1)
            try:
                return near(xp, x)
            finally:
                in_column.on = False
        return lm_fit(fun, *a, **k) if near is None else lm_fit(fun, *a, near=column, **k)
    problem.lm_fit = lm
    try:
        f = pb.fit({"mass_kg": 25.0, "damping_n_s_per_m": 50.0}, {"coulomb_friction": {"force_n": 3.0}}, max_iter=4)
    finally:
        problem.lm_fit = lm_fit
    assert columns, "the fit's columns were evaluated as any other point"
    assert len(column_runs) == len(columns), (len(column_runs), len(columns))
    assert abs(f.fx["coulomb_friction"]["force_n"] / FRICTION_N - 1) < 0.1, f.fx


def test_from_the_refined_states_a_model_is_the_refined_one():
    """At the point itself, the residual simulated from its refined states is the refined evaluation's: a column's
    difference is the parameter's alone."""
    pb = _friction_problem()
    lin, fx = {"mass_kg": 20.0, "damping_n_s_per_m": 60.0}, {"coulomb_friction": {"force_n": FRICTION_N}}
    r, X0 = pb._residual_fit(lin, fx)
    assert X0 is not None
    r2, X2 = pb._residual_fit(lin, fx, states=X0)
    assert X2 is X0
    assert np.array_equal(r, r2)
    assert np.sqrt(np.mean(r ** 2)) < 3 * NOISE_M


def test_a_play_alone_is_refined_at_every_column():
    """A play without friction is refined from the data's states even when given refined ones: from states as they
    are, a play's fit named a base resonance beside it (rig prove --plant emps_axis.toml seed 1, a10)."""
    ax = Axis(mass_kg=20.0, damping_n_s_per_m=60.0, gain_n_per_unit=1.0, backlash_m=7e-4)
    u = band_noise(1000.0, 12.0, 0.3, 30.0, 40.0, seed=5).cmd_V
    cmd, pos = simulate_axis(ax, 1000.0, command=u, sensor=Sensor(noise_m=NOISE_M, offset_m=3e-4, seed=2))
    pb = problem.Problem(cmd, pos, 1000.0, parse_plant(PLANT, "axis.toml"), np.ones(len(pos), bool), noise=NOISE_M)
    lin, fx = {"mass_kg": 20.0, "damping_n_s_per_m": 60.0}, {"backlash": {"width_m": 7e-4}}
    _, X0 = pb._residual_fit(lin, fx)
    steps = []                # each refinement step reads the play anew (the drive itself: one simulation)
    read = pb.plant.read
    pb.plant.read = lambda *a, **k: steps.append(1) or read(*a, **k)
    pb._residual_fit({**lin, "mass_kg": 20.1}, fx, states=X0)
    assert len(steps) > 1
