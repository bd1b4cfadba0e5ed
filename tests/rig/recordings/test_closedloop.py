"""rig.recordings.closedloop: feedback from the measured position to the command, from the file's attributes or the data."""
import numpy as np
from scipy.signal import lfilter

from rig.recordings import closedloop

FS = 2000.0


def _plant(u: np.ndarray) -> np.ndarray:
    """A lightly damped second-order discrete plant (a stand of a few tens of Hz), one sample of delay."""
    return lfilter([0.0, 0.002], [1.0, -1.95, 0.96], u)


def test_open_loop_command_is_not_flagged():
    rng = np.random.default_rng(1)
    u = rng.standard_normal(40_000)
    y = _plant(u) + 0.01 * rng.standard_normal(len(u))
    ev = closedloop.check(u, y, FS)
    assert ev.closed is False and ev.statistic is not None and ev.statistic < closedloop.THRESHOLD


def test_command_computed_from_the_measured_position_is_flagged():
    rng = np.random.default_rng(2)
    n = 40_000
    r = rng.standard_normal(n)
    noise = 0.05 * rng.standard_normal(n)   # the sensor noise the controller feeds back
    b, a = [0.0, 0.002], [1.0, -1.95, 0.96]
    x = np.zeros(n)                     # plant output without noise
    y = np.zeros(n)                     # measured position
    u = np.zeros(n)
    for k in range(2, n):
        x[k] = -a[1] * x[k - 1] - a[2] * x[k - 2] + b[1] * u[k - 1]
        y[k] = x[k] + noise[k]
        u[k] = r[k] - 5.0 * y[k]        # the controller answers the position of its own sample
    ev = closedloop.check(u, y, FS)
    assert ev.closed is True and ev.statistic > 2 * closedloop.THRESHOLD
    assert "reacts to the measured position" in ev.reason


def test_rig_run_recordings_are_closed_loop_by_their_attributes():
    ev = closedloop.check(np.zeros(10), np.zeros(10), FS, {"command": "rig run", "isolation_at_start": "on"})
    assert ev.closed and "rig run" in ev.reason and ev.as_dict()["closed_loop"] is True


def test_too_short_says_so():
    ev = closedloop.check(np.ones(100), np.arange(100.0), FS)
    assert ev.closed is False and "too short" in ev.reason


def test_the_recordings_own_word_counts_where_the_data_are_too_short():
    """A plant file's [signals] reference or closed_loop marks the data closed loop (Recording.closed_loop):
    a 100 Hz, 10 s log is too short for the data test, the file's word still names the loop."""
    ev = closedloop.check(np.ones(1000), np.arange(1000.0), 100.0, stated="position PID with a current loop")
    assert ev.closed is True and ev.statistic is None and "position PID with a current loop" in ev.reason
    assert closedloop.check(np.ones(1000), np.arange(1000.0), 100.0).closed is False


def test_identify_through_a_plant_file_names_a_closed_loop_the_file_states(tmp_path):
    """rig identify --plant on a short closed-loop log at 100 Hz: the map's reference makes the report say so."""
    from rig.diagnose.refit import identify_plant
    from rig.plant.file import load_subject
    rng = np.random.default_rng(3)
    n, fs, m, c = 1000, 100.0, 5.0, 20.0
    ref = np.where((np.arange(n) // 200) % 2, 0.01, -0.01)
    x = v = 0.0
    rows = []
    for k in range(n):                                     # a P-D position loop on a free mass, force in N
        u = 400.0 * (ref[k] - x) - 40.0 * v + 0.5 * rng.standard_normal()
        rows.append(f"{k / fs:.3f},{u:.6f},{x:.9f},{ref[k]:.4f}")
        v += (u - c * v) / m / fs
        x += v / fs
    (tmp_path / "log.csv").write_text("t,force,pos,ref\n" + "\n".join(rows) + "\n")
    plant_toml = tmp_path / "axis.toml"
    plant_toml.write_text('[plant]\nfamily = "mechanical_axis"\ninput_unit = "N"\n'
                          'mass_kg = { value = 4.0, min = 1.0, max = 50.0 }\n'
                          'damping_n_s_per_m = { value = 10.0, min = 1.0, max = 200.0 }\n'
                          '[signals]\ntime = "t"\ncommand = { name = "force", unit = "N" }\n'
                          'position = { name = "pos", unit = "m" }\nreference = { name = "ref", unit = "m" }\n')
    subject = load_subject(tmp_path / "log.csv", plant_toml)
    out = identify_plant(subject.rec, subject.plant)
    assert out["closed_loop"]["closed_loop"] is True and "says so" in out["closed_loop"]["reason"]
    assert "closed-loop data" in out["warning"]
