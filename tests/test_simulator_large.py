"""The large-skin scene: touched fraction, moving contacts, idle taxels' noise as the dense physics
gives it, reproducibility and chunk invariance."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import signal, stats

from touchreal.raw import RawChunk, taxel_grid
from touchreal.simulator.eskin import FS_HZ, ContactInput, ESkin, SkinParams, _ou
from touchreal.simulator.idle import arma_of_sum, standard_normal
from touchreal.simulator.large import LargeSkinSource, large_scene, reach_mm
from touchreal.sources.live import SimHops


def arrays(c: RawChunk) -> tuple[np.ndarray, ...]:
    return c.st_t, c.st, c.pvdf_t, c.pvdf


@pytest.mark.parametrize("touched", [0.01, 0.05, 0.25, 1.0])
def test_the_touched_fraction_is_the_one_asked(touched):
    xy = taxel_grid(4096)
    scene = large_scene(xy, touched, seed=3)
    fractions = [scene.touched(xy, t).mean() for t in np.linspace(1.0, 60.0, 60)]
    assert np.mean(fractions) == pytest.approx(touched, rel=0.1)
    assert large_scene(xy, 0.0, seed=3).n_contactors == 0


def test_probes_follow_the_touched_taxels_and_never_overlap():
    xy = taxel_grid(65536)
    few, many = large_scene(xy, 0.01, seed=1), large_scene(xy, 0.25, seed=1)
    assert 1 < few.n_contactors < many.n_contactors
    c = many.centres(np.linspace(0, 30, 50))  # (t, K, 2): footprints stay apart at all times
    gap = np.linalg.norm(c[:, :, None] - c[:, None, :], axis=-1) + np.eye(many.n_contactors) * 1e9
    assert gap.min() >= 2 * many.radius_mm.max()


def test_contacts_move_across_the_skin():
    xy = taxel_grid(4096)
    scene = large_scene(xy, 0.05, seed=2)
    path = scene.centres(np.linspace(1.0, 20.0, 400))
    assert np.all(np.ptp(path, axis=0).max(axis=1) > 50.0)  # every probe travels several pitches
    a, b = scene.touched(xy, 1.0), scene.touched(xy, 5.0)
    assert a.any() and b.any() and not np.array_equal(a, b)


def test_touched_taxels_feel_the_contact_and_untouched_ones_read_noise():
    xy = taxel_grid(400)
    src = LargeSkinSource(xy, 0.05, seed=4)
    raw = src.read(1.5)
    under = src.scene.touched(xy, raw.st_t[-1])
    far = np.ones(len(xy), bool)
    for c, h, r in zip(src.scene.centres(raw.st_t[-1])[0], src.scene.half_mm, src.scene.radius_mm):
        far &= np.hypot(*(xy - c).T) > np.hypot(*h) + r + reach_mm() + 20.0
    assert under.any() and far.any()
    assert raw.st[-1, under].min() > 0.2  # pressed
    assert raw.st[-1, far].max() < 0.15  # the baseline offset and noise


def test_no_contact_is_noise_only_and_every_taxel_stays_idle():
    src = LargeSkinSource(taxel_grid(64), 0.0, seed=1)
    raw = src.read(0.5)
    assert src.active.size == 0
    assert raw.st.max() < 0.15 and np.abs(raw.pvdf).max() < 0.1


def test_idle_taxels_have_the_noise_hum_and_drift_of_the_dense_physics():
    # fixed mains amplitudes (no random level), so one instance's hum can be compared
    skin = dataclasses.replace(SkinParams(), mains_v_log_sd=0.0, mains_taxel_log_sd=0.0, mains_hz_sd=0.0)
    xy, n = taxel_grid(64), 12000
    cheap = LargeSkinSource(xy, 0.0, seed=5, skin=skin, t0_s=0.0).advance(n)
    dense = ESkin(xy, skin, seed=6, t0_s=0.0, initial_depth_mm=-1.0).process(ContactInput.still(n, -1.0))
    t = np.arange(n) / FS_HZ
    basis = np.stack([np.sin(2 * np.pi * 50 * t), np.cos(2 * np.pi * 50 * t), np.ones(n)], 1)

    def stats_of(raw: RawChunk) -> np.ndarray:
        pv = raw.pvdf.astype(float)
        coef = np.linalg.lstsq(basis, pv, rcond=None)[0]
        hum = np.hypot(coef[0], coef[1]).mean()  # 50 Hz amplitude (V)
        white = np.diff(pv, axis=0).std() / np.sqrt(2)  # broadband noise (V)
        drift = pv.reshape(6, n // 6, -1).mean(axis=1).std()  # slow wander of 1 s means (V)
        st = raw.st - raw.st.mean(axis=0)
        return np.array([hum, white, drift, st.std(), raw.st.mean()])

    assert stats_of(cheap) == pytest.approx(stats_of(dense), rel=0.15)


def test_the_one_noise_process_has_the_autocovariance_of_the_three():
    p = SkinParams()
    ou = [(_ou(p.pv_wander_tau_s, 1.0, FS_HZ)[2], p.pv_wander_v), (_ou(p.pv_flicker_tau_s, 1.0, FS_HZ)[2], p.pv_flicker_v)]
    b, a = arma_of_sum(p.pv_noise_v, ou)
    impulse = signal.lfilter(b, a, np.r_[1.0, np.zeros(60000)])
    lags = np.array([0, 1, 2, 5, 20, 100, 1000])
    got = [impulse[: impulse.size - k] @ impulse[k:] for k in lags]
    want = sum(sd**2 * phi**lags for phi, sd in ou) + np.where(lags == 0, p.pv_noise_v**2, 0.0)
    assert np.allclose(got, want, rtol=1e-6)


def test_the_ziggurat_draws_standard_normals():
    x = np.empty(400_000)
    standard_normal(np.array([7, 11], np.uint64), x)
    assert abs(x.mean()) < 0.01 and x.std() == pytest.approx(1.0, abs=0.01)
    assert stats.kstest(x, "norm").pvalue > 0.001
    assert (np.abs(x) > 3).mean() == pytest.approx(2 * stats.norm.sf(3), rel=0.15)


def test_same_seed_identical_different_seed_differs():
    xy = taxel_grid(100)
    a, b, c = (LargeSkinSource(xy, 0.1, seed=s).read(0.3) for s in (8, 8, 9))
    for x, y in zip(arrays(a), arrays(b)):
        assert np.array_equal(x, y)
    assert not np.array_equal(a.pvdf, c.pvdf)


def test_irregular_reads_give_the_samples_of_one_read():
    # long enough for taxels to come within reach and retire (quiet time ~1.2 s)
    xy = taxel_grid(144)
    whole = LargeSkinSource(xy, 0.25, seed=7).advance(5000)
    src = LargeSkinSource(xy, 0.25, seed=7)
    rng = np.random.default_rng(1)
    parts, left = [], 5000
    while left:
        n = min(int(rng.choice([0, 1, 7, 10, 20, 33, 64, 400])), left)
        parts.append(src.advance(n))
        left -= n
    for x, y in zip(arrays(whole), arrays(RawChunk.concat(parts))):
        assert np.array_equal(x, y)


def test_sim_hops_play_the_large_scene_on_request():
    hops = SimHops(256, 0.005, seed=1, touched=0.05)
    chunks = [hops.read_hop() for _ in range(30)]
    pv = np.concatenate([c.pvdf_t for c in chunks])
    assert np.allclose(np.diff(pv), 1 / FS_HZ)
    assert all(c.pvdf.shape[1] == 256 for c in chunks)
    assert isinstance(SimHops(4, 0.005).scene.eskin, ESkin)  # None: the default scene
