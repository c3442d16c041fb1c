"""Proof that a parameter set runs: the whole online chain on a short synthetic input.

A set can be valid field by field and still fail in the pipeline (a filter design that does not
exist, an encoder whose state overflows). :func:`prove_runnable` drives the same
:class:`~touchreal.stream.StreamEncoder` the service runs, with every class and every window of the
set active and channels on, through silence, saturation (force at full scale, PVDF at both rails)
and a full-scale vibration, in chunks of the set's update interval, then flushes it. Any exception
or a non-finite channel, spike stamp or state value refuses the set. It also compiles the numba
kernels, so the service uses it as its warm-up.
"""

from __future__ import annotations

import numpy as np

from .params import EncoderParams, ParamsError
from .raw import RawChunk
from .settings import PVDF_FS_HZ, PVDF_RANGE_V, ST_FS_HZ, ST_RANGE_N
from .stream import StreamEncoder

DRY_RUN_TAXELS = 2  #: taxel 0: silence, saturation, vibration; taxel 1: the opposite rails
SEGMENT_S = 0.4  #: duration of each of the three input segments (s)


def synthetic_input(n_taxels: int = DRY_RUN_TAXELS, segment_s: float = SEGMENT_S) -> RawChunk:
    """Raw samples (s, N, V) of three segments of ``segment_s`` each: silence (0 N, 0 V);
    saturation (force at full scale, PVDF at its upper rail on even taxels, lower on odd ones);
    a full-scale 250 Hz PVDF vibration over a force ramp (half the taxels in antiphase)."""
    st_t = np.arange(int(round(3 * segment_s * ST_FS_HZ))) / ST_FS_HZ
    pv_t = np.arange(int(round(3 * segment_s * PVDF_FS_HZ))) / PVDF_FS_HZ
    sign = np.where(np.arange(n_taxels) % 2 == 0, 1.0, -1.0)
    st_seg, pv_seg = np.minimum(st_t // segment_s, 2), np.minimum(pv_t // segment_s, 2)
    f_max, v_max = ST_RANGE_N[1], PVDF_RANGE_V[1]
    ramp = f_max * (st_t - 2 * segment_s) / segment_s
    st = np.select([st_seg == 0, st_seg == 1], [0.0, f_max], ramp)[:, None] * np.ones(n_taxels)
    vib = v_max * np.sin(2 * np.pi * 250.0 * pv_t)
    pvdf = np.select([pv_seg == 0, pv_seg == 1], [0.0, v_max], vib)[:, None] * sign
    return RawChunk(st_t, st, pv_t, pvdf)


def prove_runnable(params: EncoderParams) -> None:
    """Run the set on :func:`synthetic_input`; raise :class:`~touchreal.params.ParamsError` naming
    why it cannot run (the exception, or where a non-finite value appeared)."""
    raw = synthetic_input()
    step_s = params.preprocess.update_ms / 1000.0
    try:
        with np.errstate(all="ignore"):  # the verdict is the finiteness checks below, not numpy's warnings
            stamps, finite = _run(params, raw, step_s)
    except ParamsError:
        raise
    except Exception as exc:  # whatever the numerics raise is a reason to refuse the set
        raise ParamsError(f"the parameter set does not run: {type(exc).__name__}: {exc}") from exc
    if not all(np.all(np.isfinite(s)) for s in stamps):
        raise ParamsError("the encoder produced non-finite spike times in the dry run")
    if not finite:
        raise ParamsError("the pipeline state became non-finite in the dry run (silence, saturation, vibration)")


def _run(params: EncoderParams, raw: RawChunk, step_s: float) -> tuple[list[np.ndarray], bool]:
    """Spike stamps (s) per chunk and whether the final state is finite; raises on non-finite channels."""
    enc = StreamEncoder(params, DRY_RUN_TAXELS)
    enc.set_active({c: range(DRY_RUN_TAXELS) for c in enc.classes}, range(DRY_RUN_TAXELS))
    stamps = []
    for t0 in np.arange(0.0, raw.st_t[-1] + step_s, step_s):
        st_sel = (raw.st_t >= t0) & (raw.st_t < t0 + step_s)
        pv_sel = (raw.pvdf_t >= t0) & (raw.pvdf_t < t0 + step_s)
        ch, ev = enc.process_channels(RawChunk(raw.st_t[st_sel], raw.st[st_sel], raw.pvdf_t[pv_sel], raw.pvdf[pv_sel]))
        if ch.n_samples and not np.all(np.isfinite(ch.data)):
            raise ParamsError(f"the preprocessing produced non-finite channels at {t0:.3f} s of the dry run")
        stamps.append(ev.t_s)
    stamps.append(enc.finish().t_s)
    finite, _, _ = enc.state_report()
    return stamps, finite
