"""Physics of the simulated e-skin: forces, quantisation, PVDF calibration, mains, spatial decay, hysteresis."""

from __future__ import annotations

import numpy as np
import pytest

from touchreal.simulator.eskin import (
    ADC_STEP_V,
    FS_HZ,
    ContactInput,
    ESkin,
    SkinParams,
    pv_radial_gain,
    st_radial_gain,
    tooth_relief,
    vibration_drive_mm,
)
from touchreal.simulator.scene import Scene, SceneEvent, SceneSource
from touchreal.simulator.simulate import conditions, simulate_trial
from touchreal.simulator.stimuli import RampHold, Robot, RobotParams, SineBurst


def tone(x: np.ndarray, f: float, fs: float) -> float:
    x = np.asarray(x, float)
    t = np.arange(x.size) / fs
    return float(2 * abs((x - x.mean()) @ np.exp(-2j * np.pi * f * t)) / x.size)


def still_force(depth_mm: float, seconds: float = 0.5, seed: int = 0) -> float:
    """Mean SingleTact reading (N) of a probe resting at ``depth_mm`` on a relaxed skin."""
    sk = ESkin(seed=seed, initial_depth_mm=depth_mm)
    raw = sk.process(ContactInput.still(int(seconds * FS_HZ), depth_mm))
    return float(raw.st.mean())


def play(stim, seconds: float, onset: float = 0.3, seed: int = 0, xy=(0.0, 0.0)):
    src = SceneSource(Scene((SceneEvent(onset, stim, xy),)), seed=seed)
    return src.advance(int(seconds * FS_HZ)).taxel(0)


def test_force_increases_with_depth_and_matches_stiffness():
    depths = [0.2, 0.5, 0.8, 1.1, 1.4, 1.7, 2.0]
    forces = [still_force(d) for d in depths]
    assert np.all(np.diff(forces) > 0.05), forces
    p = SkinParams()
    # long-term force k * d^n (+ the ~0.04 N baseline offset), within the per-taxel stiffness spread
    for d, f in zip(depths, forces):
        assert f == pytest.approx(p.stiffness_n_mm * d**p.exponent + p.st_offset_n, rel=0.1, abs=0.03)
    assert forces[depths.index(1.4)] == pytest.approx(4.1, rel=0.1)  # rig-v1: 4.14 N at 1.4 mm


def test_hold_force_of_ramps_is_monotone_in_depth():
    holds = []
    for d in (0.8, 1.2, 1.6, 2.0):
        raw = play(RampHold(d, 40.0, 40.0, 1.0), 2.0)
        sel = (raw.st_t > 1.0) & (raw.st_t < 1.3)
        holds.append(raw.st[sel].mean())
    assert np.all(np.diff(holds) > 0.5), holds


def test_singletact_quantised_and_clipped_pvdf_on_adc_grid():
    raw = play(RampHold(3.5, 40.0, 40.0, 0.5), 1.8)  # k * 3.5^1.78 ~ 19 N: beyond the range
    st = raw.st.astype(float)
    assert np.allclose(st * 100, np.round(st * 100), atol=1e-3)
    assert st.max() == pytest.approx(10.0)
    assert np.sum(st == np.float32(10.0)) >= 40  # saturated through the hold
    assert st.min() >= 0.0
    assert not np.any(np.signbit(raw.st))  # no -0.0
    codes = raw.pvdf.astype(float) / ADC_STEP_V
    assert np.allclose(codes, np.round(codes), atol=1e-3)
    assert raw.pvdf.min() >= -1.65 and raw.pvdf.max() <= 1.65
    # after a deep press the relaxing silicone pulls the reading below zero: clipped at 0 N
    tail = raw.st[raw.st_t > 1.45]
    assert np.all(tail == 0.0)


def test_pvdf_amplitude_matched_across_sine_frequencies():
    amps, drives = {}, {}
    for cond in conditions("sine"):
        f = cond.stimulus.freq_hz
        entry, tr = simulate_trial(cond, 0, "s", seed=int(f), reference=False)
        sel = (tr.pvdf_t > entry["onset_s"] + 0.1) & (tr.pvdf_t < entry["stim_end_s"] - 0.1)
        amps[f] = tone(tr.pvdf[sel], f, FS_HZ)
        drives[f] = cond.stimulus.drive_mm
    target = SkinParams().sine_target_v
    for f, a in amps.items():
        assert a == pytest.approx(target, rel=0.3), (f, a)
    assert max(amps.values()) / min(amps.values()) < 1.5, amps
    # ...while the physical exciter displacement differs a lot between frequencies
    assert max(drives.values()) / min(drives.values()) > 3.0, drives


def test_mains_hum_odd_harmonics_over_broadband_floor():
    sk = ESkin(seed=4)
    raw = sk.process(ContactInput.still(int(4 * FS_HZ), 0.0))
    x = raw.pvdf[:, 0]
    a = {f: tone(x, f, FS_HZ) for f in (50, 60, 100, 150, 200, 250, 300, 350, 77)}
    p = SkinParams()
    assert a[50] == pytest.approx(p.mains_v, rel=0.7)
    assert a[50] > 10 * a[60] and a[50] > 10 * a[77]  # a line, not broadband
    assert a[150] > 2 * a[100] and a[250] > 2 * a[200] and a[350] > 2 * a[300]  # odd >> even
    assert 0.004 < x.std() < 0.015  # rig-v1 baseline rms ~0.008 V


def test_radial_decay_steeper_for_singletact_than_pvdf():
    st, pv = {}, {}
    for r in (30.0, 0.0, 4.0, 8.0):  # same seed: same sensor offsets; r = 30 mm is the zero-force reference
        raw = play(SineBurst.calibrated(90.0), 1.8, onset=0.4, xy=(r, 0.0))
        st[r] = raw.st[raw.st_t < 0.35].mean() - st.get(30.0, 0.0)
        sel = (raw.pvdf_t > 0.5) & (raw.pvdf_t < 1.3)
        pv[r] = tone(raw.pvdf[sel], 90.0, FS_HZ)
    assert st[4.0] / st[0.0] < 0.5 and st[8.0] / st[0.0] < 0.05
    assert pv[4.0] / pv[0.0] > 0.45 and pv[8.0] / pv[0.0] > 0.15
    assert st[8.0] / st[0.0] < pv[8.0] / pv[0.0]
    # the gain functions themselves: SingleTact edge near its 4 mm rim, film decays gradually
    r = np.array([0.0, 2.0, 4.0, 6.0, 8.0])
    g_st, g_pv = st_radial_gain(r), pv_radial_gain(r)
    assert np.all(np.diff(g_st) < 0) and np.all(np.diff(g_pv) < 0)
    assert g_st[3] < 0.05 < g_pv[3]


def test_high_frequencies_decay_faster_with_distance():
    ratio = {}
    for f in (90.0, 265.0):
        amp = {}
        for r in (0.0, 8.0):
            raw = play(SineBurst.calibrated(f), 1.8, onset=0.4, xy=(r, 0.0), seed=2)
            sel = (raw.pvdf_t > 0.5) & (raw.pvdf_t < 1.3)
            amp[r] = tone(raw.pvdf[sel], f, FS_HZ)
        ratio[f] = amp[8.0] / amp[0.0]
    assert ratio[265.0] < 0.85 * ratio[90.0], ratio


def test_anisotropy_is_mild():
    sk = ESkin(seed=0)
    g = []
    for th in np.radians([0, 90, 180, 270]):
        c = ContactInput.still(2, 1.0, (6.0 * np.cos(th), 6.0 * np.sin(th)))
        g.append(sk._geometry(c)[1][0, 0])
    g = np.array(g)
    assert 0.02 < (g.max() - g.min()) / g.mean() < 0.4


def test_hysteresis_release_slower_than_press():
    raw = play(RampHold(1.5, 40.0, 40.0, 0.6), 1.6)
    t, f = raw.st_t, raw.st.astype(float)
    top = f[(t > 0.7) & (t < 0.9)].mean()

    def crossing(level: float, rising: bool, after: float) -> float:
        idx = np.flatnonzero((t > after) & ((f >= level) if rising else (f <= level)))[0]
        return t[idx - 1] + (level - f[idx - 1]) / (f[idx] - f[idx - 1]) * (t[idx] - t[idx - 1])

    rise = crossing(0.9 * top, True, 0.3) - crossing(0.1 * top, True, 0.3)
    release = 0.3 + 1.5 / 40.0 + 0.6
    fall = crossing(0.1 * top, False, release) - crossing(0.9 * top, False, release)
    assert fall > 1.3 * rise, (rise, fall)
    # and the force follows the command with a delay (silicone + robot + sensor), > 20 ms
    assert crossing(0.5 * top, True, 0.3) - (0.3 + 0.5 ** (1 / 1.78) * 1.5 / 40.0) > 0.02


def test_robot_cannot_reach_commanded_velocity_instantly():
    robot = Robot(RobotParams())
    t = np.arange(int(0.3 * FS_HZ)) / FS_HZ
    cmd = 95.0 * t  # 95 mm/s ramp from rest
    depth, _ = robot.track(cmd, np.zeros_like(t))
    v = np.gradient(depth, 1 / FS_HZ)
    assert v[t < 0.02].max() < 0.6 * 95.0
    assert v[t > 0.2].mean() == pytest.approx(95.0, rel=0.03)
    assert np.all(depth <= cmd + 1e-9)


def test_same_seed_same_arrays_different_seed_differs():
    c = ContactInput.still(3000, 0.0)
    c.depth_mm[1000:2000] = 1.0
    a = ESkin(seed=11).process(c)
    b = ESkin(seed=11).process(c)
    d = ESkin(seed=12).process(c)
    assert np.array_equal(a.pvdf, b.pvdf) and np.array_equal(a.st, b.st) and np.array_equal(a.st_t, b.st_t)
    assert not np.array_equal(a.pvdf, d.pvdf)


def test_tooth_relief_is_a_smoothed_square():
    x = np.linspace(0, 4, 4001)
    sharp = tooth_relief(x, np.full_like(x, 2.0), 1e-4)
    assert np.mean(np.abs(np.abs(sharp) - 1) < 0.05) > 0.95  # square wave for a thin layer
    smooth = tooth_relief(x, np.full_like(x, 2.0), 0.5)
    fund = tone(smooth, 1 / 2.0, 1 / (x[1] - x[0]))
    assert fund == pytest.approx(4 / np.pi * np.exp(-2 * np.pi * 0.5 / 2.0), rel=0.02)
    assert np.all(tooth_relief(x, np.zeros_like(x), 0.5) == 0)


def test_drive_calibration_uses_the_small_signal_gain():
    p = SkinParams(drive_calibration_sd=0.0)
    for f in (10.0, 100.0, 400.0):
        stim = SineBurst(f, vibration_drive_mm(f, 0.43, p), preload_mm=0.43)
        raw = play(stim, 1.8, onset=0.4, seed=3)
        sel = (raw.pvdf_t > 0.5) & (raw.pvdf_t < 1.3)
        assert tone(raw.pvdf[sel], f, FS_HZ) == pytest.approx(p.sine_target_v, rel=0.15)
