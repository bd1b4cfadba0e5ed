"""VC curves (controllers/vibration_criteria.py) on signals whose one-third-octave velocity is known
analytically."""
from __future__ import annotations

import math

import numpy as np
import pytest

from controllers.vibration_criteria import (CRITERIA, NONE_MET, band_velocity_rms, band_velocity_rms_from_psd,
                                           criterion_um_s, plot_vc, third_octave_bands, vc_class, vc_report)

FS = 1000.0


def test_bands_are_the_base_ten_third_octaves():
    nominal, fc, lo, hi = third_octave_bands(1.0, 100.0)
    assert list(nominal) == [1, 1.25, 1.6, 2, 2.5, 3.15, 4, 5, 6.3, 8, 10, 12.5, 16, 20, 25, 31.5, 40, 50, 63, 80,
                             100]
    assert np.allclose(hi[:-1], lo[1:])                          # contiguous
    assert np.allclose(hi / lo, 10 ** 0.1)                       # one-third octave (base 10)
    assert np.allclose(fc / nominal, 1.0, atol=0.03)


@pytest.mark.parametrize("f0, band", [(10.0, 10.0), (31.6227766, 31.5), (1.0, 1.0), (79.4328, 80.0)])
def test_sine_displacement_lands_in_its_band(f0, band):
    """x = A sin(2 pi f0 t): all of its rms velocity, 2 pi f0 A / sqrt(2), in the band centred on f0."""
    A = 2e-6
    t = np.arange(int(200 * FS)) / FS
    fc, v = band_velocity_rms(A * np.sin(2 * np.pi * f0 * t), FS, kind="displacement")
    k = list(fc).index(band)
    assert v[k] == pytest.approx(2 * np.pi * f0 * A / math.sqrt(2), rel=0.01)
    others = np.delete(v, k)
    assert np.all(others < 0.02 * v[k])


def test_sine_acceleration_is_integrated():
    """a = A sin(2 pi f0 t) (an accelerometer's record): rms velocity A / (2 pi f0) / sqrt(2) in its band."""
    A, f0 = 3e-3, 12.589254
    t = np.arange(int(100 * FS)) / FS
    fc, v = band_velocity_rms(A * np.sin(2 * np.pi * f0 * t), FS, kind="acceleration")
    assert v[list(fc).index(12.5)] == pytest.approx(A / (2 * np.pi * f0) / math.sqrt(2), rel=0.01)


def test_white_velocity_noise_gives_the_bandwidth():
    """Velocity white at one-sided PSD S: band rms sqrt(S x bandwidth), statistically."""
    rng = np.random.default_rng(7)
    sigma = 1e-5
    x = rng.normal(0.0, sigma, int(400 * FS))
    S = sigma ** 2 / (FS / 2)
    fc, v = band_velocity_rms(x, FS, kind="velocity", segment_s=20.0)
    _, _, lo, hi = third_octave_bands(1.0, 100.0)
    expect = np.sqrt(S * (hi - lo))
    assert np.all(np.abs(v / expect - 1) < 0.15)
    assert np.mean(v / expect) == pytest.approx(1.0, abs=0.03)


def test_psd_integration_is_exact_for_a_flat_spectrum():
    f = np.geomspace(0.5, 150.0, 3000)
    S = np.full_like(f, 4e-12)
    fc, v = band_velocity_rms_from_psd(f, S, kind="velocity")
    _, _, lo, hi = third_octave_bands()
    assert np.allclose(v, np.sqrt(4e-12 * (hi - lo)), rtol=1e-9)
    # a displacement PSD falling as 1/f^2 is flat in velocity
    fc, v2 = band_velocity_rms_from_psd(f, S / (2 * np.pi * f) ** 2, kind="displacement")
    assert np.allclose(v2, v, rtol=1e-3)


def test_criterion_lines():
    f = np.array([1.0, 4.0, 8.0, 80.0, 100.0])
    assert np.allclose(criterion_um_s("operating theatre (ISO)", f), [1600.0, 200.0, 100.0, 100.0, 100.0])
    assert np.allclose(criterion_um_s("office (ISO)", f), 4 * criterion_um_s("operating theatre (ISO)", f))
    assert np.allclose(criterion_um_s("VC-D", f), 6.25)
    levels = [lvl for _, lvl, _ in CRITERIA]
    assert levels == sorted(levels, reverse=True)                 # least to most stringent
    with pytest.raises(ValueError, match="VC-Z"):
        criterion_um_s("VC-Z", f)


def test_class_met():
    fc, _, _, _ = third_octave_bands()
    assert vc_class(np.full(len(fc), 5.0), fc) == "VC-D"
    assert vc_class(np.full(len(fc), 6.25), fc) == "VC-D"
    assert vc_class(np.full(len(fc), 6.3), fc) == "VC-C"
    assert vc_class(np.full(len(fc), 0.5), fc) == "VC-G"
    one_band = np.full(len(fc), 1.0)
    one_band[10] = 30.0                                           # one band above VC-B
    assert vc_class(one_band, fc) == "VC-A"
    low = np.full(len(fc), 90.0)
    low[0] = 1500.0                                               # ISO lines allow more at 1 Hz
    assert vc_class(low, fc) == "operating theatre (ISO)"
    assert vc_class(np.full(len(fc), 900.0), fc) == NONE_MET


def test_report_and_plot(tmp_path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    t = np.arange(int(30 * FS)) / FS
    rep = vc_report({"off": 5e-6 * np.sin(2 * np.pi * 20 * t), "on": 5e-7 * np.sin(2 * np.pi * 20 * t)}, FS)
    assert rep["vc_class"] == {"off": "workshop (ISO)", "on": "VC-A"}   # 444 and 44 um/s rms at 20 Hz
    v20 = rep["velocity_um_s"]["off"][rep["band_hz"].index(20.0)]
    assert v20 == pytest.approx(2 * np.pi * 20 * 5 / math.sqrt(2), rel=0.01)
    fig, ax = plt.subplots()
    plot_vc(ax, rep, title="test")
    p = tmp_path / "vc.png"
    fig.savefig(p)
    plt.close(fig)
    assert p.stat().st_size > 10000


def test_bad_input():
    with pytest.raises(ValueError, match="kind"):
        band_velocity_rms(np.zeros(100), FS, kind="jerk")
    with pytest.raises(ValueError, match="1-D"):
        band_velocity_rms(np.zeros((10, 2)), FS)
