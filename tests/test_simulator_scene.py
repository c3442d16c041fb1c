"""Live simulated source: chunk invariance, reproducibility, clock, taxel arrays, scene script, pacer."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import shipped_notch_gain

from touchreal.simulator.eskin import FS_HZ
from touchreal.raw import RawChunk
from touchreal.raw import taxel_grid
from touchreal.simulator.scene import RealTimePacer, Scene, SceneEvent, SceneSource, default_scene
from touchreal.simulator.stimuli import RampHold, RobotParams, SineBurst, TextureSlide


def short_scene() -> Scene:
    """A 3.2 s loop with a press, a burst and a slide, so a few seconds cover every code path."""
    return Scene(
        (
            SceneEvent(0.1, RampHold(1.0, 65.0, 40.0, 0.2), (0.0, 0.0)),
            SceneEvent(0.6, SineBurst.calibrated(120.0, resting=False, burst_s=0.4), (3.0, 0.0)),
            SceneEvent(1.9, TextureSlide(2.0, slide_s=0.5), (0.0, 0.0)),
        ),
        loop_s=3.2,
    )


def arrays(c: RawChunk) -> tuple[np.ndarray, ...]:
    return c.st_t, c.st, c.pvdf_t, c.pvdf


def test_irregular_chunks_equal_one_read():
    xy = taxel_grid(3, 6.0)
    whole = SceneSource(short_scene(), taxels_xy_mm=xy, seed=7).read(7.0)
    src = SceneSource(short_scene(), taxels_xy_mm=xy, seed=7)
    rng = np.random.default_rng(1)
    parts, total = [], 0.0
    while total < 7.0:
        d = min(float(rng.choice([0.0, 0.00013, 0.0005, 0.0071, 0.032, 0.25, 0.9])), 7.0 - total)
        parts.append(src.read(d))
        total += d
    joined = RawChunk.concat(parts)
    for a, b in zip(arrays(whole), arrays(joined)):
        assert a.shape == b.shape
        assert np.array_equal(a, b)


def test_advance_in_ticks_equals_read():
    a = SceneSource(short_scene(), seed=3)
    b = SceneSource(short_scene(), seed=3)
    whole = a.advance(8000)
    parts = [b.advance(n) for n in (1, 19, 20, 333, 0, 4000, 3627)]
    for x, y in zip(arrays(whole), arrays(RawChunk.concat(parts))):
        assert np.array_equal(x, y)
    # after advance(), read() continues at the next tick
    nxt = b.read(0.01)
    assert nxt.pvdf_t[0] == pytest.approx(whole.pvdf_t[-1] + 1 / FS_HZ)
    assert nxt.pvdf.shape[0] == 20


def test_same_seed_identical_different_seed_differs():
    a = SceneSource(seed=5).read(3.0)
    b = SceneSource(seed=5).read(3.0)
    c = SceneSource(seed=6).read(3.0)
    for x, y in zip(arrays(a), arrays(b)):
        assert np.array_equal(x, y)
    assert not np.array_equal(a.pvdf, c.pvdf)


def test_one_clock_regular_and_continuous():
    src = SceneSource(short_scene(), seed=9)
    c1, c2 = src.read(0.5), src.read(0.5)
    st_t = np.concatenate([c1.st_t, c2.st_t])
    pv_t = np.concatenate([c1.pvdf_t, c2.pvdf_t])
    assert 0 <= pv_t[0] < 1 / FS_HZ and 0 <= st_t[0] < 0.01
    assert np.allclose(np.diff(pv_t), 1 / FS_HZ) and np.allclose(np.diff(st_t), 0.01)
    assert pv_t.size == 2000 and st_t.size == 100
    assert pv_t[-1] < 1.0 <= pv_t[-1] + 1 / FS_HZ
    # SingleTact samples fall on PVDF ticks (one clock)
    assert np.all(np.min(np.abs(st_t[:, None] - pv_t[None, :]), axis=1) < 1e-9)
    assert c1.st.dtype == np.float32 and c1.pvdf.dtype == np.float32


def test_taxel_array_streams_follow_radial_attenuation():
    xy = np.array([[0.0, 0.0], [5.0, 0.0], [25.0, 0.0]])
    scene = Scene((SceneEvent(0.2, RampHold(1.5, 40.0, 40.0, 1.0), (0.0, 0.0)),))
    raw = SceneSource(scene, taxels_xy_mm=xy, seed=1).read(1.6)
    assert raw.st.shape == (160, 3) and raw.pvdf.shape == (3200, 3) and raw.n_taxels == 3
    hold = (raw.st_t > 0.8) & (raw.st_t < 1.2)
    f = raw.st[hold].mean(axis=0)
    assert f[0] > 3.0 and f[1] < 0.3 * f[0] and f[2] < 0.1
    press = (raw.pvdf_t > 0.2) & (raw.pvdf_t < 0.4)
    peak = np.abs(raw.pvdf[press]).max(axis=0)
    assert peak[0] > peak[1] > peak[2]
    assert peak[1] > 0.2 * peak[0]  # the film decays gradually
    one = raw.taxel(1)
    assert one.st.shape == (160,) and np.array_equal(one.pvdf, raw.pvdf[:, 1])


def test_default_scene_script_and_loop():
    sc = default_scene()
    kinds = {type(e.stimulus).__name__ for e in sc.events}
    assert kinds == {"RampHold", "SineBurst", "TextureSlide"}
    depths = {e.stimulus.depth_mm for e in sc.events if isinstance(e.stimulus, RampHold)}
    assert len(depths) >= 3
    freqs = {e.stimulus.freq_hz for e in sc.events if isinstance(e.stimulus, SineBurst)}
    assert len(freqs) >= 2
    assert sc.loop_s is not None
    t = np.linspace(0, sc.loop_s, 997)
    a, b = sc.command(t, RobotParams()), sc.command(t + 3 * sc.loop_s, RobotParams())
    assert np.allclose(a["depth"], b["depth"]) and np.allclose(a["vib"], b["vib"])
    assert a["depth"].max() > 1.5 and a["vib"].std() > 0 and a["comb"].any()
    several = default_scene(positions_mm=[(0, 0), (10, 0)])
    assert {e.xy_mm for e in several.events} == {(0.0, 0.0), (10.0, 0.0)}


def test_live_source_produces_plausible_signals():
    raw = SceneSource(seed=2).read(default_scene().loop_s).taxel(0)
    assert raw.st.max() > 5.0  # the 1.8 mm press
    assert raw.st.min() == 0.0  # released skin
    assert np.abs(raw.pvdf).max() > 0.1  # transients and vibration
    assert raw.st.size == pytest.approx(100 * default_scene().loop_s, abs=1)


def test_scene_rejects_overlaps():
    ramp = RampHold(1.0, 10.0, 10.0, 1.0)  # 1.2 s long
    with pytest.raises(ValueError):
        Scene((SceneEvent(0.1, ramp), SceneEvent(1.0, ramp)))
    with pytest.raises(ValueError):
        Scene((SceneEvent(0.1, ramp),), loop_s=1.0)


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0
        self.sleeps: list[float] = []

    def clock(self) -> float:
        return self.now

    def sleep(self, dt: float) -> None:
        self.sleeps.append(dt)
        self.now += dt


def test_pacer_sleeps_to_wall_clock_and_streams_seamlessly():
    fake = FakeClock()
    pacer = RealTimePacer(SceneSource(short_scene(), seed=4), chunk_s=0.032, clock=fake.clock, sleep=fake.sleep)
    chunks = []
    for i, c in enumerate(pacer):
        chunks.append(c)
        fake.now += 0.005  # consumer work
        if i == 9:
            fake.now += 0.1  # a stall: the next chunks come without sleeping
        if i == 30:
            pacer.stop()
    assert len(chunks) == 31
    assert fake.sleeps[0] == pytest.approx(0.032)
    assert all(s == pytest.approx(0.027) for s in fake.sleeps[1:9])
    assert len(fake.sleeps) < 31  # caught up after the stall without sleeping
    joined = RawChunk.concat(chunks)
    ref = SceneSource(short_scene(), seed=4).read(31 * 0.032)
    for a, b in zip(arrays(joined), arrays(ref)):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("mains_hz", [50.0, 60.0])
def test_the_default_scripts_vibrations_pass_the_shipped_mains_notches(mains_hz):
    # a burst on a notched harmonic is removed with the hum (a 250 Hz burst on 50 Hz mains: PC barely fires)
    freqs = [ev.stimulus.freq_hz for ev in default_scene().events if isinstance(ev.stimulus, SineBurst)]
    assert len(freqs) == 3
    for f in freqs:
        assert shipped_notch_gain(mains_hz, f) > 0.95, f
