"""Reference-model mechanics: Sneddon punch, stress field, surface wave; against TouchSim's own arrays."""

from __future__ import annotations


import numpy as np
import pytest

from touchreal.reference.constants import load_constants
from touchreal.reference.mechanics import (
    probe_load,
    profile_velocity,
    propagate,
    sneddon_compliance,
    stress_gain,
    wave_decay,
    wave_delay_samples,
)

A = 0.5  # mm, probe radius
DEPTHS = np.array([0.3, 1.6, 2.0])  # mm, SA1 / RA / PC


def test_compliance_and_load():
    d0 = sneddon_compliance(A, 0.05, 0.4)
    assert d0 == pytest.approx((1 - 0.16) / (2 * 0.5 * 0.05))  # 16.8 mm/N
    s = np.array([-0.2, 0.0, 0.5, 1.0])
    np.testing.assert_allclose(probe_load(s, d0), s / 16.8, rtol=1e-15)  # odd in S0, N
    with pytest.raises(ValueError):
        sneddon_compliance(0.0)


def test_stress_at_surface_centre_is_the_punch_centre_pressure():
    # Sneddon: under the centre of a flat punch the surface pressure is P / (2 pi a^2).
    g = stress_gain(0.0, 1e-9, A)
    assert g == pytest.approx(1.0 / (2 * np.pi * A * A), rel=1e-6)


@pytest.mark.parametrize("depth", [0.3, 1.6, 2.0])
def test_vertical_stress_carries_the_whole_load(depth):
    # Force balance: the vertical stress integrated over any horizontal plane equals the load.
    r = np.concatenate([np.linspace(0, 20, 400_001)[:-1], np.geomspace(20, 5000, 200_001)])
    f = stress_gain(r, depth, A) * 2 * np.pi * r
    total = np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(r))
    assert total == pytest.approx(1.0, rel=2e-4)


def test_stress_decays_with_distance_and_depth():
    r = np.linspace(0, 10, 2001)
    outside = r >= A
    for z in DEPTHS:
        g = stress_gain(r, z, A)
        assert np.all(g > 0)
        assert np.all(np.diff(g[outside]) < 0)  # beyond the probe edge: monotonic decay
        if z >= A:
            assert np.all(np.diff(g) < 0)
        else:  # shallow: the flat punch's edge concentration puts the peak under the rim
            assert 0 < r[np.argmax(g)] <= A
    z = np.linspace(A, 5, 100)  # on the axis, below one probe radius: monotonic decay with depth
    assert np.all(np.diff(stress_gain(0.0, z, A)) < 0)
    with pytest.raises(ValueError):
        stress_gain(0.0, 0.0, A)


def test_profile_velocity_central_difference_and_ends():
    fs = 5000.0
    s = np.array([0.0, 0.0, 1.0, 3.0, 3.0, 3.0]) * 1e-3
    v = profile_velocity(s, fs)
    expect = np.array([0.0, 0.5, 1.5, 1.0, 0.0, 0.0]) * 1e-3 * fs
    expect[0], expect[-1] = expect[1], expect[-2]
    np.testing.assert_allclose(v, expect)
    ramp = np.arange(100) * 0.002  # 10 mm/s at 5 kHz
    np.testing.assert_allclose(profile_velocity(ramp, fs), 10.0)
    assert np.all(profile_velocity(np.array([1.0, 2.0]), fs) == 0)


def test_wave_delay_and_decay():
    # (dist - a) / 8 m/s in 5 kHz samples, rounded half to even like numpy.rint
    d = np.array([0.0, 0.5, 1.0, 4.5, 8.5, 16.5])
    np.testing.assert_array_equal(wave_delay_samples(d, A, 5000.0, 8000.0), [0, 0, 0, 2, 5, 10])
    dec = wave_decay(np.array([0.0, 0.5, 0.5 + 1e-12, 1.0, 10.0]), A)
    assert dec[0] == dec[1] == pytest.approx(1 / (2 * A))
    assert dec[2] == pytest.approx(1 / (2 * A), rel=1e-5)  # continuous at the probe edge (sqrt cusp)
    assert dec[3] == pytest.approx(np.arcsin(0.5) / (np.pi * A))
    assert np.all(np.diff(dec[1:]) <= 0)


def test_propagate_delays_and_scales_an_impulse():
    fs = 5000.0
    trace = np.zeros(200)
    trace[50] = 0.01  # velocity doublet around sample 50
    aff = np.array([[0.0, 0.0], [8.5, 0.0], [0.0, 16.5]])
    static, dynamic = propagate(trace, (0.0, 0.0), aff, DEPTHS, pin_radius_mm=A, fs_hz=fs)
    assert static.shape == dynamic.shape == (200, 3, 3)
    d0 = sneddon_compliance(A)
    pdyn = profile_velocity(trace, fs) / d0
    for loc, delay in zip(range(3), [0, 5, 10]):
        dist = np.hypot(*aff[loc])
        for j, z in enumerate(DEPTHS):
            expect = np.zeros(200)
            expect[delay:] = pdyn[: 200 - delay] * wave_decay(dist, A) / z**2
            np.testing.assert_allclose(dynamic[:, loc, j], expect, rtol=1e-14, atol=0)
    # static: instantaneous, proportional to the load, largest under the probe and shallow
    assert np.argmax(static[:, 0, 0]) == 50
    assert static[50, 0, 0] > static[50, 0, 1] > static[50, 0, 2] > 0
    assert static[50, 0, 0] > static[50, 1, 0] > static[50, 2, 0]


# ---- against TouchSim's own mechanical components ------------------------------------------



@pytest.mark.shared
def test_packaged_constants_equal_shared_constants(shared):
    packaged = load_constants()
    theirs = load_constants(shared / "touchsim" / "constants.json")
    np.testing.assert_array_equal(packaged.params, theirs.params)
    np.testing.assert_array_equal(packaged.ihbasis, theirs.ihbasis)
    np.testing.assert_array_equal(packaged.depth_mm, theirs.depth_mm)
    assert packaged.model_class.tolist() == ["SA1"] * 4 + ["RA"] * 9 + ["PC"] * 4


@pytest.mark.shared
def test_static_and_dynamic_match_touchsim(conformance):
    root, stimuli = conformance
    c = load_constants()
    worst_s = worst_d = 0.0
    for s in stimuli:
        with np.load(root / s["file"]) as d:
            static, dynamic = propagate(d["trace"], d["probe_xy"], d["aff_xy"], c.depth_mm,
                                        pin_radius_mm=float(d["pin_radius"]), fs_hz=float(d["fs"]))
            ref_s, ref_d = d["static"], d["dynamic"]
        assert static.shape == ref_s.shape and dynamic.shape == ref_d.shape
        worst_s = max(worst_s, np.abs(static - ref_s).max() / np.abs(ref_s).max())
        worst_d = max(worst_d, np.abs(dynamic - ref_d).max() / np.abs(ref_d).max())
        # exact zeros before the wave arrives / where TouchSim has them
        assert np.array_equal(dynamic == 0, ref_d == 0), s["id"]
    assert worst_s < 1e-13 and worst_d < 1e-13, (worst_s, worst_d)
