"""Synthetic raw recordings for tests that must run without ../shared, and what the shipped PVDF notches pass."""

from __future__ import annotations

import numpy as np

from scipy.signal import sosfreqz

from touchreal.params import default_params
from touchreal.preprocess.filters import mains_notches
from touchreal.recording import Trial
from touchreal.settings import PVDF_FS_HZ


def synthetic_trial(duration_s: float = 1.5, seed: int = 0, freq_hz: float = 200.0, depth_n: float = 3.0) -> Trial:
    """A press-hold-release force (N, 100 Hz) with a PVDF transient + vibration burst (V, 2 kHz)."""
    rng = np.random.default_rng(seed)
    st_t = 0.004 + np.arange(int(duration_s * 100)) / 100.0
    pv_t = 0.0003 + np.arange(int(duration_s * 2000)) / 2000.0

    def force(t):
        up = np.clip((t - 0.3) / 0.1, 0, 1)
        down = np.clip((t - 0.9) / 0.15, 0, 1)
        return depth_n * (up - down)

    st = np.round(np.clip(force(st_t) + rng.normal(0, 0.01, st_t.size), 0, 10) / 0.01) * 0.01
    dforce = np.gradient(force(pv_t), pv_t)
    burst = ((pv_t > 0.5) & (pv_t < 0.8)) * 0.05 * np.sin(2 * np.pi * freq_hz * pv_t)
    mains = 0.004 * np.sin(2 * np.pi * 50 * pv_t) + 0.002 * np.sin(2 * np.pi * 150 * pv_t + 1)
    pvdf = 0.004 * dforce + burst + mains + rng.normal(0, 0.003, pv_t.size)
    cmd = np.zeros(int(duration_s * 5000), np.float32)
    return Trial(st_t=st_t, st=st.astype(np.float32), pvdf_t=pv_t, pvdf=pvdf.astype(np.float32), cmd_depth=cmd)


def shipped_notch_gain(mains_hz: float, freq_hz: float) -> float:
    """|H| at ``freq_hz`` of the shipped parameters' mains notches on ``mains_hz`` mains."""
    p = default_params().preprocess
    sos = mains_notches(mains_hz, p.notch_harmonics, p.notch_q, PVDF_FS_HZ).sos
    return float(abs(sosfreqz(sos, worN=[freq_hz], fs=PVDF_FS_HZ)[1][0]))
