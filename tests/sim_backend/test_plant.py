"""Foundation: the time-domain plants against Eq. 10, the effect switches, the machine (Eq. 15)."""
import math

import numpy as np
import pytest

from rig.config import Config
from sim_backend.actuator import Effects, StandPlant, linear_chirp, simulate_stand
from sim_backend.linear import actuator_params, g_eha_frf
from sim_backend.machine import load_modal_model
from sim_backend.rig_plant import (I_STROKE, I_TABLE, I_TOOL, I_X, FloorMotion, RigPlant, rig_state_space,
                                   simulate_rig)

FS = 2000.0
P = actuator_params()


def _frf(cmd, pos, fs, f):
    """Exact FRF of a system at rest by the FFT ratio of a record padded until the response has died out."""
    n = len(cmd)
    U = np.fft.rfft(cmd, 4 * n)
    Y = np.fft.rfft(pos, 4 * n)
    fr = np.fft.rfftfreq(4 * n, 1 / fs)
    idx = np.searchsorted(fr, f)
    return (Y / U)[idx], fr[idx]


def _padded_chirp(seconds=20.0, amp=1.0, fs=FS):
    _, u = linear_chirp(fs, seconds, 0.5, 100.0, amp)
    return np.concatenate([u, np.zeros(int(3 * fs))])


@pytest.fixture(scope="module")
def chirp_linear():
    u = _padded_chirp()
    return u, simulate_stand(P, u, FS)["position_m"]


def test_time_domain_frf_matches_eq10_with_zoh(chirp_linear):
    u, y = chirp_linear
    f = np.linspace(1.0, 80.0, 60)
    H, fr = _frf(u, y, FS, f)
    w = 2 * np.pi * fr
    T = 1 / FS
    zoh = np.sinc(w * T / (2 * np.pi)) * np.exp(-0.5j * w * T)      # ZOH: sinc magnitude, half-sample delay
    G = g_eha_frf(P, w) * zoh
    err_db = 20 * np.log10(np.abs(H) / np.abs(G))
    err_deg = np.angle(H / G, deg=True)
    assert np.max(np.abs(err_db)) < 0.2
    assert np.max(np.abs(err_deg)) < 1.0


def test_delay_adds_phase_lag_w_tau_and_no_gain(chirp_linear):
    u, y0 = chirp_linear
    tau = 1.7e-3
    y = simulate_stand(P, u, FS, Effects(delay_s=tau))["position_m"]
    f = np.linspace(2.0, 80.0, 40)
    H0, fr = _frf(u, y0, FS, f)
    H1, _ = _frf(u, y, FS, f)
    r = H1 / H0
    assert np.max(np.abs(20 * np.log10(np.abs(r)))) < 0.05
    lag = -np.unwrap(np.angle(r))
    assert np.allclose(lag, 2 * np.pi * fr * tau, atol=math.radians(0.5))


def _sine_gain(fx, amp_V, f_hz=5.0, seconds=2.0, fs=FS):
    t = np.arange(int(seconds * fs)) / fs
    u = amp_V * np.sin(2 * np.pi * f_hz * t)
    y = simulate_stand(P, u, fs, fx)["position_m"]
    half = len(t) // 2                                       # steady state: the second half, whole periods
    c = np.exp(-2j * np.pi * f_hz * t[half:])
    Y1 = 2 * np.mean(y[half:] * c)
    Y3 = 2 * np.mean(y[half:] * c ** 3)
    return abs(Y1) / amp_V, abs(Y3) / abs(Y1)


def test_saturation_lowers_gain_at_large_amplitude_only():
    lin_small, _ = _sine_gain(Effects(), 0.5)
    lin_large, h3_lin = _sine_gain(Effects(), 3.0)
    sat = Effects(saturation_limit_ma=3.0)                   # K_v * 3 V = 6 mA > 3 mA
    g_small, _ = _sine_gain(sat, 0.5)
    g_large, h3 = _sine_gain(sat, 3.0)
    assert g_small == pytest.approx(lin_small, rel=1e-3)
    assert g_large < 0.85 * lin_large
    assert h3 > 10 * h3_lin + 0.01                           # odd harmonics appear


def test_deadband_lowers_gain_at_small_amplitude_only():
    db = Effects(deadband_width_ma=0.6)
    lin, _ = _sine_gain(Effects(), 0.5)
    g_small, _ = _sine_gain(db, 0.5)                         # 1 mA peak against 0.6 mA overlap
    g_large, _ = _sine_gain(db, 5.0)                         # 10 mA peak
    assert g_small < 0.6 * lin
    assert g_large > 0.9 * lin and g_large < lin


def test_coulomb_friction_distorts_at_low_velocity():
    fr = Effects(friction_force_n=400.0)
    lin, h3_lin = _sine_gain(Effects(), 0.2, f_hz=1.0, seconds=4.0)
    g, h3 = _sine_gain(fr, 0.2, f_hz=1.0, seconds=4.0)
    assert h3 > 10 * h3_lin                                  # odd harmonics from the velocity reversals
    assert g < lin                                           # the seal force opposes the motion
    g_weak, _ = _sine_gain(Effects(friction_force_n=4.0), 0.2, f_hz=1.0, seconds=4.0)
    assert abs(g_weak / lin - 1) < 0.1 * abs(g / lin - 1)    # scales with the friction force


def test_base_resonance_is_linear_and_local():
    u = _padded_chirp(amp=1.0)
    fx = Effects(base_frequency_hz=58.0, base_damping_ratio=0.03)
    y1 = simulate_stand(P, u, FS, fx)["position_m"]
    y2 = simulate_stand(P, 2.0 * u, FS, fx)["position_m"]
    y0 = simulate_stand(P, u, FS)["position_m"]
    f = np.array([5.0, 40.0, 55.0, 58.0, 61.0, 75.0])
    H0, _ = _frf(u, y0, FS, f)
    H1, _ = _frf(u, y1, FS, f)
    H2, _ = _frf(2 * u, y2, FS, f)
    dev_db = 20 * np.log10(np.abs(H1 / H0))
    assert abs(dev_db[0]) < 0.2                              # far below: unchanged
    assert np.max(np.abs(dev_db[2:5])) > 1.0                 # near the stand mode: a clear feature
    assert np.allclose(H1, H2, rtol=1e-6)                    # the same at any amplitude


def test_periodic_disturbance_is_a_line_unrelated_to_the_command():
    fs, f_d = 1000.0, 31.0
    n = int(4 * fs)
    y = simulate_stand(P, np.zeros(n), fs, Effects(disturbance_frequency_hz=f_d,
                                                      disturbance_force_n=300.0))["position_m"]
    spec = np.abs(np.fft.rfft(y[n // 2:] * np.hanning(n // 2)))
    fr = np.fft.rfftfreq(n // 2, 1 / fs)
    assert fr[np.argmax(spec)] == pytest.approx(f_d, abs=1.0)
    assert np.max(np.abs(y)) > 1e-10
    assert np.all(simulate_stand(P, np.zeros(n), fs)["position_m"] == 0.0)


def test_sensor_noise_rms():
    r = simulate_stand(P, np.zeros(20000), 1000.0, Effects(position_noise_m=2e-8, accel_noise_mps2=2e-4, seed=3))
    assert np.std(r["position_m"]) == pytest.approx(2e-8, rel=0.05)
    assert np.std(r["accel_mps2"]) == pytest.approx(2e-4, rel=0.05)


# ---- the machine and the four-mount rig -------------------------------------------------------------

def test_modal_receptance_is_eq15_with_table2():
    mm = load_modal_model().flexible_only()
    s = 1 / math.sqrt(1000.0)                                # Table 2 read in 1/sqrt(t) -> SI
    fl = np.array([-0.0434, 0.20, -0.0224, 0.12, 0.0713]) * s
    fr = np.array([-0.0441, -0.198, -0.0183, -0.10, 0.0004]) * s
    wn = 2 * np.pi * np.array([20, 26, 31, 56, 68.0])
    w = 2 * np.pi * np.array([1.0, 20.0, 26.0, 45.0, 100.0])
    ref = np.array([np.sum(fl * fr / (-wk ** 2 + 2j * 0.03 * wk * wn + wn ** 2)) for wk in w])
    assert np.allclose(mm.receptance(mm.phi_mounts[:, 0], mm.phi_mounts[:, 1], w), ref, rtol=1e-12)


def test_rig_modes_flexible_and_machine_on_actuators():
    ss = rig_state_space(Config())
    ev = np.linalg.eigvals(ss.A)
    assert np.max(ev.real) < 0                               # passive rig (valves at null) is stable
    f = np.abs(ev.imag) / (2 * np.pi)
    # flexible yaw and heave modes stay at Table 2's 20 and 31 Hz
    assert np.min(np.abs(f - 20.0)) < 0.5 and np.min(np.abs(f - 31.0)) < 0.5
    # the 16 t machine on the actuators' stiffness: heave near the paper's loaded w_h (~251 Hz by formula)
    heave = f[(f > 200) & (f < 350)]
    assert len(heave) >= 6 and np.min(np.abs(heave - 251.4)) < 25


def test_passive_transmissibility_is_unity_at_low_frequency():
    ss = rig_state_space(Config())
    _, Gg = ss.ground_frf(2 * np.pi * np.array([0.5, 1.0]))
    one = np.ones(4)
    for out in (I_TABLE + 1, I_TOOL + 1, I_X):
        assert np.allclose(np.abs(Gg[:, out, :] @ one), 1.0, atol=0.01)
    assert np.allclose(np.abs(Gg[:, I_STROKE, :] @ one), 0.0, atol=0.01)


def test_rig_plant_step_equals_batch_and_floor_rms():
    cfg = Config()
    dt = 1 / 5000
    floor = FloorMotion(dt, rms_m=10e-6, seed=4)
    plant = RigPlant(cfg, dt, floor=floor, accel_noise_mps2=0.0, stroke_noise_m=0.0)
    n = 4000
    rng = np.random.default_rng(0)
    cmd = 0.05 * rng.standard_normal((n, 4))
    table, xg = [], []
    for k in range(n):
        table.append(plant.table_m)
        xg.append(plant.floor_m)
        plant.step(cmd[k].tolist())
    g = FloorMotion(dt, rms_m=10e-6, seed=4).next_block(n)
    assert np.allclose(np.array(xg), g[:, :4])
    Y = simulate_rig(cfg, dt, cmd, g[:, :4], g[:, 4:8], outputs=[I_TABLE + 1])
    assert np.allclose(table, Y[:, 0], atol=1e-12)
    long = FloorMotion(dt, rms_m=10e-6, seed=5).next_block(50000)
    assert np.std(long[:, :4]) == pytest.approx(10e-6, rel=0.1)


@pytest.mark.parametrize("fx, f0_hz, f1_hz, amp_V", [
    (Effects(delay_s=1.3e-3, saturation_limit_ma=4.0, friction_force_n=200.0), 0.5, 60.0, 2.5),
    (Effects(base_frequency_hz=58.0, base_damping_ratio=0.03, disturbance_frequency_hz=31.0,
             disturbance_force_n=250.0), 20.0, 80.0, 2.0),
])
def test_stepped_stand_equals_batch(fx, f0_hz, f1_hz, amp_V):
    _, u = linear_chirp(1000.0, 2.0, f0_hz, f1_hz, amp_V)
    ref = simulate_stand(P, u, 1000.0, fx)
    sp = StandPlant(P, fx, 1000.0)
    pos = [sp.position_m]
    for v in u[:-1]:
        sp.step(v)
        pos.append(sp.position_m)
    assert np.allclose(pos, ref["position_m"], atol=1e-15)


def _floor_run(cfg, n, dt, **kw):
    plant = RigPlant(cfg, dt, floor=FloorMotion.from_config(cfg, dt), seed=3, **kw)
    rec = {"floor": [], "floor_accel": [], "accel": [], "table": []}
    u = [0.01, -0.02, 0.0, 0.005]
    for _ in range(n):
        plant.step(u)
        rec["floor"].append(plant.floor_m)
        rec["floor_accel"].append(plant.floor_accel_mps2)
        rec["accel"].append(plant.accel_mps2)
        rec["table"].append(plant.table_m)
    return {k: np.array(v) for k, v in rec.items()}


def test_floor_accelerometer_reads_the_floor_acceleration_with_its_own_noise():
    """[sensors] floor_accel: the floor accelerometer at each mount reads the second derivative of the floor
    motion there, in step with it (a fourth-order stencil agrees within 0.5 % rms), plus white noise of its
    configured density from a generator of its own: fitting the sensors changes nothing else the plant
    computes."""
    import dataclasses
    dt, n = 1 / 5000, 1 << 15
    base = Config()
    fitted = base.replace(sensors=dataclasses.replace(base.sensors, floor_accel=True))
    clean = _floor_run(fitted, n, dt, floor_noise_mps2=0.0)
    noisy = _floor_run(fitted, n, dt)
    without = _floor_run(base, n, dt)
    x = clean["floor"]                          # the second derivative by a fourth-order stencil
    want = (-x[4:] + 16 * x[3:-1] - 30 * x[2:-2] + 16 * x[1:-3] - x[:-4]) / (12 * dt * dt)
    got = clean["floor_accel"][2:-2]
    assert np.std(got - want) < 0.005 * np.std(want)
    sigma = fitted.sensors.floor_noise_mps2_per_rthz * math.sqrt(0.5 / dt)
    assert np.std(noisy["floor_accel"] - clean["floor_accel"]) == pytest.approx(sigma, rel=0.05)
    for key in ("floor", "accel", "table"):
        assert np.array_equal(noisy[key], without[key])
    assert np.all(without["floor_accel"] == 0.0)                    # not fitted: nothing read


def test_plant_error_moves_the_simulated_actuators_only():
    """[plant_error]: the simulated rig's actuator parameters are the configured ones times the factors; the
    model the controllers are designed on (rig_state_space of the config) stays as configured."""
    import dataclasses
    cfg = Config()
    off = cfg.replace(plant_error=dataclasses.replace(cfg.plant_error, K_Q=1.1, K_C=0.9, w_nv=1.1))
    plant = RigPlant(off, 1 / 5000)
    assert plant.ss.act.K_Q == pytest.approx(1.1 * cfg.valve.K_Q) and plant.ss.act.K_C == pytest.approx(
        0.9 * cfg.valve.K_C) and plant.ss.act.w_nv == pytest.approx(1.1 * cfg.valve.w_nv)
    assert plant.ss.act.K_L == cfg.actuator.K_L and plant.ss.act.zeta == cfg.valve.zeta
    assert rig_state_space(off).act.K_Q == cfg.valve.K_Q
    assert np.array_equal(RigPlant(cfg, 1 / 5000).ss.A, rig_state_space(cfg).A)
