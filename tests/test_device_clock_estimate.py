"""DeviceClock (sans-I/O lower-envelope fit of a device clock against host receive times):
synthetic links with drift, offsets, exponential jitter, stalls and fixed transport delay."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from touchreal.device.clock_estimate import FLOOR_US, HORIZON_US, WINDOW_US, ClockEstimate, DeviceClock

SETTLE_S = 3.0  #: the documented settling time (s of device time)
BOUND_US = 1000  #: the documented error bound after settling (jitter mean <= 5 ms, stalls, |drift| <= 200 ppm)
STATED_MAX_US = 3000  #: the stated error after settling stays below this


def link(
    seconds: float, drift_ppm: float, jitter_ms: float, stall_p: float, seed: int, x0: int = 123_456, h0: float = 5e12,
    min_delay_us: float = 80.0, rate_hz: tuple[int, ...] = (100, 200),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(device us of each frame's newest sample, host us of its arrival, host us of its acquisition).

    The device clock runs ``drift_ppm`` fast; each frame is delayed by ``min_delay_us`` plus an
    exponential of mean ``jitter_ms``; with probability ``stall_p`` per frame the link stalls 5..80 ms
    (every frame acquired meanwhile waits for its end); frames arrive in order (a serial line)."""
    rng = np.random.default_rng(seed)
    x = np.unique(np.concatenate([np.arange(0, seconds * 1e6, 1e6 / r) + 500 * i for i, r in enumerate(rate_hz)]))
    x = x0 + x.astype(np.int64)
    acq = h0 + (x - x0) / (1 + drift_ppm * 1e-6)
    arrive = acq + min_delay_us + rng.exponential(jitter_ms * 1e3, x.size) if jitter_ms > 0 else acq + min_delay_us
    for s in np.nonzero(rng.random(x.size) < stall_p)[0]:
        end = acq[s] + rng.uniform(5e3, 80e3)
        held = (acq >= acq[s]) & (acq < end)
        arrive[held] = np.maximum(arrive[held], end)
    return x, np.floor(np.maximum.accumulate(arrive)).astype(np.int64), acq + min_delay_us


def errors(x: np.ndarray, host: np.ndarray, truth: np.ndarray, every: int = 40) -> np.ndarray:
    """(seconds since the first frame, estimate - truth, stated error) at every ``every``-th frame."""
    dc, out = DeviceClock(), []
    for i in range(x.size):
        dc.add(int(x[i]), int(host[i]))
        if i % every == 0 and (e := dc.estimate(int(x[i]))) is not None:
            out.append(((x[i] - x[0]) / 1e6, e.host_us - truth[i], e.error_us))
    return np.array(out)


@settings(max_examples=40, deadline=None)
@given(
    drift_ppm=st.floats(-200, 200),
    jitter_ms=st.floats(0, 5),
    stall_p=st.sampled_from([0.0, 0.002, 0.01, 0.03]),
    x0=st.integers(0, 1 << 40),
    h0=st.floats(0, 2e15),
    seed=st.integers(0, 2**32 - 1),
)
def test_after_settling_the_estimate_is_within_the_bound_and_its_stated_error(drift_ppm, jitter_ms, stall_p, x0, h0, seed):
    x, host, truth = link(8.0, drift_ppm, jitter_ms, stall_p, seed, x0=x0, h0=h0)
    err = errors(x, host, truth)
    settled = err[err[:, 0] >= SETTLE_S]
    assert np.all(np.abs(settled[:, 1]) <= BOUND_US), np.abs(settled[:, 1]).max()
    assert np.all(np.abs(settled[:, 1]) <= settled[:, 2])  # the stated error covers the true one
    assert np.all(settled[:, 2] <= STATED_MAX_US)


def test_rate_and_offset_of_a_100_ppm_device_over_a_minute_of_bursty_jitter():
    x, host, truth = link(70.0, 100.0, 2.0, 0.01, seed=11, rate_hz=(100,))
    dc = DeviceClock()
    for xi, hi in zip(x, host):
        dc.add(int(xi), int(hi))
    e = dc.estimate(int(x[-1]))
    assert e is not None and e.epoch == 0 and dc.resets == 0
    assert e.rate == pytest.approx(1 / (1 + 100e-6), abs=2e-6)
    assert abs(e.host_us - truth[-1]) <= 100 and e.error_us <= 400
    assert len(dc._minima) <= HORIZON_US // WINDOW_US  # bounded memory: one point per window of the horizon


def test_estimate_is_provisional_before_two_windows_and_restart_starts_a_new_epoch():
    dc = DeviceClock()
    assert dc.estimate(0) is None
    dc.add(1_001_000, 1_050_400)
    dc.add(1_002_000, 1_051_000)
    dc.add(1_300_000, 1_349_300)
    # provisional until two windows are complete: rate 1 through the fastest frame, error = lag spread
    assert dc.estimate(1_400_000) == ClockEstimate(1_400_000, 1_449_000, 1.0, FLOOR_US + 400 + 398, 0)  # 1000 ppm of 398 ms
    x, host, truth = link(3.0, -50.0, 1.0, 0.0, seed=2)
    for xi, hi in zip(x, host):
        dc.add(int(xi), int(hi))
    assert dc.resets == 1 and dc.epoch == 1  # device time went backwards: a new clock
    dc.mark_jump()
    e = dc.estimate(int(x[-1]))
    assert e is not None and e.epoch == 2 and abs(e.host_us - truth[-1]) <= e.error_us
    dc.reset()
    assert dc.estimate(int(x[-1])) is None and dc.epoch == 3 and dc.resets == 1


def test_a_forward_jump_of_the_device_clock_resets_instead_of_bending_the_line():
    x, host, truth = link(6.0, 30.0, 1.0, 0.0, seed=3)
    jump = x.size // 2
    x[jump:] += 3_000_000  # firmware bug: the device clock leaps 3 s ahead within a session
    dc = DeviceClock()
    for xi, hi in zip(x, host):
        dc.add(int(xi), int(hi))
    assert dc.resets == 1 and dc.epoch == 1
    e = dc.estimate(int(x[-1]))
    assert e is not None and abs(e.host_us - truth[-1]) <= e.error_us


def test_invalid_windows_are_refused():
    with pytest.raises(ValueError, match="window"):
        DeviceClock(window_us=0)
    with pytest.raises(ValueError, match="horizon"):
        DeviceClock(window_us=1000, horizon_us=1500)
