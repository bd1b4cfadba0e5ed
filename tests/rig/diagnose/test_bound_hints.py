"""What the diagnosis says of a plant file's free parameter the refit left at a bound of its range."""
from types import SimpleNamespace

from rig.diagnose.verdict import file_bound_hints as _file_bound_hints
from rig.diagnose.plants import at_bounds

BOUNDS = {"den1": (0.0, 50.0), "mass_kg": (5.0, 100.0), "damping_n_s_per_m": (5.0, 500.0)}


def test_at_bounds_names_the_parameters_within_one_percent_of_a_bound_and_which_bound():
    lin = {"den1": 0.3, "mass_kg": 99.5, "damping_n_s_per_m": 250.0}
    assert at_bounds(BOUNDS, lin, BOUNDS) == {"den1": 0.0, "mass_kg": 100.0}
    assert at_bounds(BOUNDS, {**lin, "den1": 0.6}, ["den1"]) == {}          # 1.2 % of the width away


def test_at_bounds_on_a_log_scale_measures_the_distance_there():
    wide = {"num0": (1e-3, 1e3)}
    assert at_bounds(wide, {"num0": 0.1}, ["num0"]) == {"num0": 1e-3}          # linear: 1e-4 of the width away
    assert at_bounds(wide, {"num0": 0.1}, ["num0"], {"num0": True}) == {}       # log: a third of the way up
    assert at_bounds(wide, {"num0": 1.05e-3}, ["num0"], {"num0": True}) == {"num0": 1e-3}


def _hints(lin):
    pb = SimpleNamespace(plant=SimpleNamespace(bounds_lin=BOUNDS, log_scale={}), lin_keys=tuple(BOUNDS))
    return _file_bound_hints(pb, SimpleNamespace(lin=lin))


def test_a_bound_of_zero_reached_is_no_such_term_not_a_different_plant():
    hints = _hints({"den1": 1e-9, "mass_kg": 40.0, "damping_n_s_per_m": 250.0})
    assert len(hints) == 1 and hints[0].startswith("The refit took den1 to 0")
    assert "no such term" in hints[0] and "different" not in hints[0]


def test_another_bound_reached_says_which_and_what_to_do():
    hints = _hints({"den1": 20.0, "mass_kg": 5.01, "damping_n_s_per_m": 499.0})
    assert hints == [
        "The refit pushed mass_kg to 5.01, the lower bound of its range in the plant file (5..100): widen the range "
        "if that value is plausible, else the plant (or its units) differs from the file's.",
        "The refit pushed damping_n_s_per_m to 499, the upper bound of its range in the plant file (5..500): widen "
        "the range if that value is plausible, else the plant (or its units) differs from the file's."]
