"""The operating modes of one mount (controllers/modes.py): the request grammar, the law's dispatch with the
isolation filters kept warm, and the take-over that makes a switch bumpless; the kernel's published state."""
from __future__ import annotations

import math

import numpy as np
import pytest

from controllers.isolation import IsolationController, make_isolation_controllers, params_from_config
from controllers.modes import (MODES, ModeRequest, OperatingModes, make_operating_controllers, modes_step,
                               parse_request)
from rig.config import config_from_dict, load_config
from rig.commands.run import LAYOUTS
from rig.errors import RigError
from rig.port import Measurements
from rig.runtime.kernel import PeriodKernel

DT = 1.0 / 5000.0
PROTO = load_config(LAYOUTS["prototype"][None])


@pytest.mark.parametrize("text,mode,kind,target", [
    ("off", "off", None, None), ("isolate", "isolate", None, None), ("hold", "hold", None, None),
    ("hold 5um", "hold", "setpoint", 5e-6), ("setpoint -3um", "hold", "setpoint", -3e-6),
    ("mode hold x=2um", "hold", "setpoint", 2e-6), ("track sine:amp=10um,freq=5", "track", "sine", None),
    ("mode track step:amp=2um", "track", "step", 2e-6), ("HOLD 1e-6m", "hold", "setpoint", 1e-6)])
def test_request_grammar(text, mode, kind, target):
    r = parse_request(text, DT)
    assert r.mode == mode
    assert (r.reference.kind if r.reference else None) == kind
    if target is not None:
        assert r.reference.target_m == pytest.approx(target)


@pytest.mark.parametrize("text,match", [("", "empty"), ("fly", "expected off, hold"), ("off now", "takes no"),
                                        ("track", "needs a reference"), ("hold sine:amp=1um,freq=2", "hold takes"),
                                        ("hold 5", "has no unit"), ("track step:amp=2", "has no unit")])
def test_request_errors(text, match):
    with pytest.raises(RigError, match=match):
        parse_request(text, DT)


def _modes(start="hold"):
    return make_operating_controllers(PROTO, DT, parse_request(start, DT))[0]


def _steps(m, st, n, a=1e-3, x=0.0):
    cf = m.coefficients()
    s = np.array(st)
    out = []
    for k in range(n):
        out.append(modes_step(s, cf, a * math.sin(0.05 * k), x + 1e-9 * math.sin(0.3 * k)))
    return out, s


@pytest.mark.parametrize("new", ["hold", "hold 3um", "isolate", "track sine:amp=2um,freq=5"])
def test_a_switch_takes_the_valve_over_from_the_last_command(new):
    """From another mode's command u (here 3.1 V) the new mode's first output is u to within what one period
    of its own dynamics adds (far below the 2 V the slew limit allows)."""
    m = _modes("off")
    st = m.switch(m.initial_state(), None, 0.0, 0.0)
    _, s = _steps(m, st, 500)                        # the isolation filters warm meanwhile
    st = m.switch(s.tolist(), parse_request(new, DT), 3.1, 1e-6, m.coefficients())
    out, _ = _steps(m, st, 1, x=1e-6)
    assert abs(out[0] - 3.1) < 0.2
    assert MODES[int(st[0])] == parse_request(new, DT).mode


def test_isolation_filters_stay_warm_outside_isolate():
    m = _modes("hold")
    st = m.switch(m.initial_state(), None, 0.0, 0.0)
    _, s = _steps(m, st, 200)
    iso = s[m._i0:]
    assert np.abs(iso[:4]).max() > 0                  # the estimate followed the accelerometer
    cold = make_operating_controllers(PROTO, DT, parse_request("hold", DT))[0]
    cold.warm = False
    _, s2 = _steps(cold, cold.switch(cold.initial_state(), None, 0.0, 0.0), 200)
    assert np.abs(s2[cold._i0:][:4]).max() == 0


def test_published_state_becomes_channels_with_nan_where_a_mount_has_none():
    cfg = config_from_dict({"layout": {"plant": "stand", "mounts": ["a", "b"]}})
    om = make_operating_controllers(cfg, DT)[0]
    iso = IsolationController(params_from_config(cfg, 1), DT, name="b")
    k = PeriodKernel(cfg, [om, iso], ("a", "b"), DT, 50)
    assert list(k.published) == ["mode", "reference_m", "tracking_error_m"]
    lay = k.layout
    assert lay.width("mode") == 2 and lay.width("reference_m") == 2
    k.states[0][:] = om.switch(k.states[0].tolist(), None, 0.0, 0.0)
    rc = k.period(Measurements(0, [0.0, 0.0], [1e-7, 2e-7], [0, 0]), 0, 0.0, 0.0, 0.0, 1, 0, flags=(1, 0, 0, 0))
    assert rc == 0
    row = k.row
    assert row[lay["mode"]] == MODES.index("hold") and math.isnan(row[lay["mode"] + 1])
    assert row[lay["reference_m"]] == 0.0 and math.isnan(row[lay["reference_m"] + 1])      # held at 0
    assert row[lay["tracking_error_m"]] == pytest.approx(-1e-7)                             # the stroke read


def test_the_machine_keeps_its_isolation_controllers():
    cs = make_isolation_controllers(config_from_dict({}), DT)
    assert len(cs) == 4 and not any(isinstance(c, OperatingModes) for c in cs)
    assert ModeRequest("hold").mode == "hold"
