"""The least size worth naming (effects.Effect.least): an effect smaller than its part's own tolerance is not a
fault, however sure the fit is of it. One rule for every effect that has one: a sensor's gain within its
calibration's uncertainty, a valve's null offset within its null tolerance, a floor's rocking within what
independent motion at the mounts gives."""
from __future__ import annotations

import math

import pytest

from rig.diagnose.machine import effects as fx
from rig.diagnose.machine.floor import FloorMotion
from rig.diagnose.machine.offsets import MountOffset


@pytest.mark.parametrize("gain, named", [
    (0.997, False), (1.0019, False), (1.015, False), (1 / 1.015, False),     # within a calibration's 1-2 %
    (1.03, True), (1 / 1.08, True), (1.25, True),                            # the proof draws 8-25 % off
    (-1.0, True), (-0.997, True)])                                          # a sign reversed is a fault
def test_a_sensor_gain_is_named_only_beyond_its_calibration_uncertainty(gain, named):
    params = {"sensor": "accel", "mount": "rear_left", "gain": gain}
    assert fx.worth_naming(fx.SENSOR_GAIN, params) is named
    assert (fx.shortfall(fx.SENSOR_GAIN, params) == "") is named
    if not named:
        assert "calibration" in fx.shortfall(fx.SENSOR_GAIN, params)


def test_effects_without_a_least_size_are_worth_naming_at_any_size():
    assert fx.VALVE_DEADBAND.size is None
    assert fx.worth_naming(fx.VALVE_DEADBAND, {"mount": "rear_left", "width_ma": 1e-6})


@pytest.mark.parametrize("offset_V, stands_out", [(0.029, False), (-0.029, False), (0.03, True), (-0.1, True)])
def test_a_valve_null_offset_stands_out_only_beyond_the_catalogue_s_least_size(offset_V, stands_out):
    """offsets.py's test reads the catalogue's least size (0.03 V), no figure of its own."""
    o = MountOffset("rear_left", offset_V, 1e-4, math.nan, 0.0)
    assert o.stands_out is stands_out
    assert fx.VALVE_NULL_OFFSET.least == 0.03


@pytest.mark.parametrize("ratio, rocking", [(1.59, False), (1.6, True), (3.0, True)])
def test_a_floor_rocks_only_beyond_the_catalogue_s_least_size(ratio, rocking):
    fm = FloorMotion(True, {}, 100, "pitch", ratio, 20.0, 1.0)
    assert fm.rocking is rocking
