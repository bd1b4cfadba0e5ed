"""Each channel's delay through the drivers' timing as configuration (rig.config.channel_delays): the
accelerometers' conversion reaches the commands `[drivers] accel_delay_periods` SYNCs later (a SYNC late in
a short period: taken at the period after next), blocks of conversions add theirs, the transducer's delay is
its own; and the lockstep run `rig hil` holds itself against carries the same delay (a later conversion
isolates less, as the controller analysis says)."""
from __future__ import annotations

import dataclasses

from rig.commands.hil import HIL_DEFAULT_CONFIG, hil_config
from rig.commands.hil_lockstep import lockstep, reductions
from rig.config import Config, channel_delays, load_config


def _cfg(cfg: Config | None = None, **drivers) -> Config:
    cfg = cfg or Config()
    return cfg.replace(drivers=dataclasses.replace(cfg.drivers, **drivers))


def test_accel_delay_is_configuration_and_adds_to_blocks():
    base_a, base_s = channel_delays(_cfg(), 2000.0)
    assert base_a == 1
    assert channel_delays(_cfg(accel_delay_periods=2), 2000.0) == (2, base_s)    # the transducer's own
    assert channel_delays(_cfg(accel_delay_periods=2, accel_fetch_every=2), 2000.0)[0] == 3
    assert channel_delays(_cfg(accel_fetch_every=4), 2000.0)[0] == 4


def test_lockstep_carries_the_accelerometers_delay():
    """hil.toml's design and floor in lockstep: one more period of delay on the accelerometers costs isolation."""
    modes = ("off", "feedback")
    out = {}
    for d in (1, 2):
        cfg = hil_config(_cfg(load_config(HIL_DEFAULT_CONFIG), accel_delay_periods=d))
        res = lockstep(cfg, 6.0, modes, 1.0, 0.05)
        assert res["fault"] is None
        out[d] = reductions(res["table_rms_m"])["feedback"]
    assert out[1] > 3.0, out                     # the default design isolates in lockstep
    assert out[2] < out[1] - 0.5, out
