"""The README's friction stand (issue 29): 400 N of Coulomb friction on the simulated actuator, a 30 s chirp at
5 kHz. The named friction's 95 % interval must hold the stand's 400 N. Before, the polish stopped 1.6 standard
errors short of the fit's minimum (403.2 N reported, the interval centred near the minimum) and the reduced
model's own bias (+6.9 N: the piston's mass neglected) sat in both: "403.2 N (95 %: 402 to 415.4)"."""
import pytest

from rig.diagnose.catalogue import stand_effects
from rig.diagnose.engine import diagnose
from rig.diagnose.report import summary
from rig.recordings.recording import Recording
from sim_backend.actuator import linear_chirp, simulate_stand
from sim_backend.linear import ActuatorParams

pytestmark = pytest.mark.slow

FS = 5000.0
FRICTION_N = 400.0


def _friction_stand(seed: int) -> Recording:
    t, cmd = linear_chirp(FS, 30.0, 0.1, 100.0, 2.0)
    fx = stand_effects({"coulomb_friction": {"force_n": FRICTION_N}}, position_noise_m=2e-8,
                       accel_noise_mps2=2e-4, seed=seed)
    y = simulate_stand(ActuatorParams(), cmd, FS, fx)
    return Recording.from_signals(cmd, y["position_m"], y["accel_mps2"], fs_hz=FS, source="stand_friction")


@pytest.mark.parametrize("seed", [0, 1])     # before: 402.4 N (400.7 to 412.9), 403.4 N (403.4 to 413.8)
def test_friction_interval_holds_the_stands_friction(seed):
    d = diagnose(_friction_stand(seed), ActuatorParams())
    named = {e.name: e for e in d.effects}
    assert list(named) == ["coulomb_friction"], summary(d)
    e = named["coulomb_friction"]
    low, high = e.interval["force_n"]
    assert low <= FRICTION_N <= high, summary(d)
    assert low <= e.parameters["force_n"] <= high
    # centred on the estimate (a bootstrap about the fit's minimum), and as wide as the noise makes it
    mid = 0.5 * (low + high)
    assert abs(mid - e.parameters["force_n"]) < 0.15 * (high - low), (low, e.parameters["force_n"], high)
    assert 5.0 < high - low < 30.0
    # the reduced model's bias was measured and taken off: it is what moved the old intervals off the truth
    assert 2.0 < e.bias["force_n"] < 15.0, e.bias
