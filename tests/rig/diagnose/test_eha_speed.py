"""What the eha diagnosis's speed rests on (issue 26, speed; the figures: docs/PROOFS.md): the linear simulator's
state in registers gives the same numbers bit for bit; the twin's stand simulation takes friction's short step only
near rest, within a tiny fraction of the noise of the fixed step; a model simulated again is taken from the last
few, as a copy."""
import math
import subprocess
import sys

import numpy as np
import pytest

from rig.diagnose import catalogue, problem
from rig.diagnose.models import driver_current, ss_model
from rig.plant import zoh
from sim_backend.actuator import (Effects, _simulate_near_rest, inner_step_s, linear_chirp, simulate_stand,
                                  stand_prm)
from sim_backend.linear import ActuatorParams
from tests.paths import RECORDINGS

P = ActuatorParams()


@pytest.mark.parametrize("base", [None, (60.0, 0.03, 280.0)])
@pytest.mark.parametrize("delay_s", [0.0, 1.3e-3])
def test_the_register_kernels_give_the_general_kernels_numbers(base, delay_s):
    Am, Bm, Cm = ss_model(P, base)
    Ad, G0, G1, m = zoh.discretise(Am, Bm, 1 / 2000.0, delay_s)
    u = driver_current(P, linear_chirp(2000.0, 5.0, 0.1, 100.0, 2.2)[1])
    general, fast = np.empty(len(u)), np.empty(len(u))
    zoh._run_ss(Ad, G0, G1, Cm, u, m, general)
    zoh._RUN_SS[len(Bm)](Ad, G0, G1, Cm, u, m, fast)
    assert np.array_equal(general, fast)
    assert np.max(np.abs(general)) > 1e-7                  # it moved


def test_the_scalar_rk4_is_the_stands_own_at_one_step():
    """_simulate_near_rest with no speed to watch and the fixed step is simulate_stand bit for bit."""
    fx = Effects(friction_force_n=300.0, delay_s=1.3e-3, saturation_limit_ma=3.5, base_frequency_hz=60.0)
    cmd = linear_chirp(2000.0, 2.0, 0.1, 100.0, 2.2)[1]
    n_sub = math.ceil(1.0 / (2000.0 * inner_step_s(P, fx)))
    pos, acc, spool = np.empty(len(cmd)), np.empty(len(cmd)), np.empty(len(cmd))
    _simulate_near_rest(cmd, 2000.0, n_sub, 1, 0.0, fx.delay_s, P.K_v, fx.saturation_limit_ma, stand_prm(P, fx),
                        pos, acc, spool)
    ref = simulate_stand(P, cmd, 2000.0, fx)
    assert np.array_equal(ref["position_m"], pos) and np.array_equal(ref["accel_mps2"], acc)
    assert np.array_equal(ref["spool_mA"], spool)


@pytest.mark.parametrize("fx", [Effects(friction_force_n=450.0), Effects(friction_force_n=800.0),
                                Effects(friction_force_n=300.0, delay_s=1.3e-3)])
def test_friction_near_rest_only_stays_on_the_fixed_steps_path(fx):
    """The piston sticks at every reversal of the chirp: the short step is taken there (and where a delayed
    command switches inside a step), and the positions stay within 1e-4 of the recordings' noise (2e-8 m) of the
    fixed short step's."""
    cmd = linear_chirp(2000.0, 10.0, 0.1, 100.0, 2.2)[1]
    fixed = simulate_stand(P, cmd, 2000.0, fx)["position_m"]
    near = simulate_stand(P, cmd, 2000.0, fx, fine_near_rest=True)["position_m"]
    assert np.max(np.abs(near - fixed)) < 2e-12
    assert np.std(fixed) > 1e-7 and not np.array_equal(near, fixed)


def test_a_model_simulated_again_is_a_copy_of_the_last():
    cmd = linear_chirp(1000.0, 5.0, 0.1, 100.0, 2.0)[1]
    pb = problem.Problem(cmd, np.zeros(len(cmd)), 1000.0, P, np.ones(len(cmd), bool), noise=2e-8)
    calls = []
    simulate = pb.plant.simulate
    pb.plant.simulate = lambda *a: calls.append(1) or simulate(*a)
    lin = dict(pb.nominal)
    fx = {"valve_deadband": {"width_ma": 0.3}}
    first = pb.simulate(lin, fx)
    first[:] = 0.0                                          # the caller's own array
    again = pb.simulate(dict(lin), {"valve_deadband": {"width_ma": 0.3}})
    assert len(calls) == 1 and np.max(np.abs(again)) > 1e-7
    other = pb.simulate(lin, {"valve_deadband": {"width_ma": 0.31}})
    assert len(calls) == 2 and not np.array_equal(other, again)
    assert catalogue.slow_in(fx)


def test_the_bench_runs_one_case_a_process(tmp_path):
    """`python -m rig.diagnose.bench RECORDING... --only I`: the I-th case alone (two versions compared case by
    case, alternately); an I beyond the cases is one line naming them."""
    rec = RECORDINGS / "p01_nominal.csv.gz"
    run = subprocess.run([sys.executable, "-m", "rig.diagnose.bench", str(rec), str(rec), "--only", "1"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    rows = [l for l in run.stdout.splitlines() if l.startswith("p01_nominal")]
    assert len(rows) == 1 and "(n = 1)" in run.stdout
    bad = subprocess.run([sys.executable, "-m", "rig.diagnose.bench", str(rec), "--only", "3"],
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and "--only 3: there are only 1 cases" in bad.stderr
    assert "Traceback" not in bad.stderr
