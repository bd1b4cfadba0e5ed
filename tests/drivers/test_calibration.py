"""The calibration `rig commission` writes, applied in the drivers' conversion (drivers/conversion.py calibrated):
the channel map, sign x scale and the offset taken off, and one line for a file that names no mount."""
from __future__ import annotations

import pytest

from drivers import conversion
from rig.config import MOUNTS
from rig.errors import ConfigError

CAL = {"accel": {"front_right": {"mount": "front_left", "sign": 1.0, "scale": 1.0, "offset_mps2": 0.0},
                 "front_left": {"mount": "front_right", "sign": 1.0, "scale": 1.0, "offset_mps2": 0.0},
                 "rear_left": {"mount": "rear_left", "sign": -1.0, "scale": 1.0, "offset_mps2": 0.5},
                 "rear_right": {"mount": "rear_right", "sign": 1.0, "scale": 9.80665, "offset_mps2": 0.0}}}


def test_a_miswired_module_reads_right_through_its_calibration():
    chs = conversion.channels(range(4), [0.5] * 4)               # 2 V per m/s^2
    fixed = conversion.calibrated(chs, CAL, "accel", MOUNTS, "mps2")
    truth = [1.0, 2.0, 3.0, 4.0]                                 # m/s^2 at each mount
    # the wiring faults: ch0/ch1 swapped, ch2 inverted with an offset of 0.5 m/s^2 as read, ch3 a g range
    raw = [2 * truth[1], 2 * truth[0], 2 * (0.5 - truth[2]), 2 * truth[3] / 9.80665]
    assert conversion.apply(fixed, raw) == pytest.approx(truth)


def test_a_calibration_naming_no_mount_is_one_line():
    with pytest.raises(ConfigError, match=r"calibration \[accel.ch9\]: expected a mount"):
        conversion.calibrated(conversion.channels(range(4), [1.0] * 4), {"accel": {"ch9": {"mount": "x"}}},
                              "accel", MOUNTS, "mps2")


@pytest.mark.parametrize("content, needle", [(None, "calibration file not found"),
                                             (b"[accel]\n# \xe9\n", "is not UTF-8 text"),
                                             (b"[accel\n", "cannot be read")])
def test_a_calibration_file_that_cannot_be_read_is_one_line(tmp_path, content, needle):
    """Was: a byte that is not UTF-8 (a comment typed in Latin-1) ended in a UnicodeDecodeError traceback."""
    path = tmp_path / "commissioning.toml"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(ConfigError, match=needle) as e:
        conversion.read_calibration(path)
    assert "commissioning.toml" in str(e.value) and "\n" not in str(e.value)
