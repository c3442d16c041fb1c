"""Spatial measures: AI_2 (eq. 12) on known angular patterns, radial profiles, response areas."""

import numpy as np
import pytest

from touchreal.analysis import spatial as sp


def _scan(radii=(2, 4, 6), angles=np.arange(0, 360, 60)):
    r, th = np.meshgrid(np.asarray(radii, float), np.asarray(angles, float), indexing="ij")
    return np.concatenate([[0.0], r.ravel()]), np.concatenate([[0.0], th.ravel()])


@pytest.mark.parametrize("angles", [np.arange(0, 360, 60), np.arange(0, 360, 30)])
@pytest.mark.parametrize("a", [0.0, 0.2, 0.6])
def test_ai2_of_cos2theta_pattern_is_half_the_modulation(a, angles):
    r, th = _scan(angles=angles)
    values = 10.0 / (1 + r) * (1 + a * np.cos(2 * np.deg2rad(th - 30.0)))
    an = sp.anisotropy(r, th, values)
    assert an.ai2 == pytest.approx(a / 2.0, abs=1e-12)  # |sum R e^{2i th}| / sum R = a/2 on equally spaced angles
    np.testing.assert_allclose(an.per_ring, a / 2.0, atol=1e-12)
    if a > 0:
        assert an.axis_deg == pytest.approx(30.0, abs=1e-9)
    # opposite directions are the same axis: a cos(theta) (first-order) pattern gives no AI_2
    first = 5.0 * (1 + 0.5 * np.cos(np.deg2rad(th)))
    assert sp.anisotropy(r, th, first).ai2 == pytest.approx(0.0, abs=1e-12)


def test_ai2_skips_silent_rings_and_centre():
    r, th = _scan()
    v = np.where(r == 6, 0.0, 1 + 0.4 * np.cos(2 * np.deg2rad(th)))
    an = sp.anisotropy(r, th, v)
    assert an.radii.tolist() == [2.0, 4.0, 6.0]
    assert np.isnan(an.per_ring[2])
    assert an.ai2 == pytest.approx(0.2)
    assert np.isnan(sp.ai2_ring(np.array([0.0, 90.0]), np.zeros(2)))


def test_radial_profile_and_angular_profile():
    r, th = _scan()
    v = 12.0 - r + np.cos(2 * np.deg2rad(th))
    radii, mean, std = sp.radial_profile(r, v)
    np.testing.assert_allclose(radii, [0, 2, 4, 6])
    np.testing.assert_allclose(mean, [13.0, 10.0, 8.0, 6.0], atol=1e-12)  # cos(2 th) averages out on 6 angles
    ang, prof, pstd = sp.angular_profile(r, th, v)
    np.testing.assert_allclose(ang, np.arange(0, 360, 60))
    assert np.mean(prof) == pytest.approx(1.0)
    assert prof[0] > 1.0 and prof[0] == pytest.approx(prof[3])  # opposite directions equal


def test_response_area_of_a_cone_matches_the_disc():
    # R = 10 - r (linear in r), sampled densely in angle: area above threshold T is pi (10 - T)^2
    radii = np.arange(1, 11, 1.0)
    angles = np.arange(0, 360, 10.0)
    r, th = _scan(radii, angles)
    v = 10.0 - r
    m = sp.interpolate_map(r, th, v, step_mm=0.05)
    for thr in (2.0, 5.0):
        assert sp.response_area(m, thr) == pytest.approx(np.pi * (10 - thr) ** 2, rel=0.03)
    sweep = sp.area_sweep(m, np.arange(1, 11))
    assert np.all(np.diff(sweep) <= 0)
    assert sweep[-1] == pytest.approx(0.0, abs=0.01)
    assert np.isnan(m.values[0, 0])  # outside the scanned disc
