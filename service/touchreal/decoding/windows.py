"""Decoding windows of recorded trials: encode each trial once, then cut it into the windows a
streaming decoder would see (the rules of :mod:`touchreal_client.features`).

* Force: one window per 32 ms step ``T`` (absolute grid) with ``window_ms <= T - t_first`` inside
  the trial (a stateful model: one per step of its own, window = step, from the recording's start); label = mean SingleTact force (N) of the samples in the last bin ``[T - 10 ms, T)``
  (the force interpolated at the bin centre when the bin holds no sample).
* Texture: counts of the model's classes (PC; SA1, RA, PC for ``spectral``) anchored at the first PC spike of the trial (re-anchored after 500 ms of PC
  silence, as online); one window per step whose
  anchored window is filled and ends by the stimulus end (manifest ``stim_end_s``); label = the
  manifest's ``texture`` (else its condition).
* Scanning texture (``spatial`` features, which read the scanning speed): windows ``[T - window, T)``
  on the 32 ms grid (no anchor) during which the surface moves at a steady speed: the trial's scan
  position (its ``cmd_x`` channel, else ``params.speed_mm_s`` between ``events.slide_start_s`` and
  ``slide_end_s``) advances in each quarter of the window by the mean within :data:`SCAN_STEADY`;
  the window's speed (mm/s) = distance / window.

Datasets are split by trial with the fitting split (:func:`touchreal.splits.split_repeats`):
no trial has windows on both sides.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from touchreal_client import features as F

from ..params import EncoderParams
from ..recording import Dataset, RecordingError, Trial
from ..splits import params_split_seed, split_repeats
from ..stream import encode_trial

SPLITS = ("heldout", "train", "all")
DEFAULT_SPLIT_SEED = 0  #: the fit's default seed, used when the parameters were not fitted on the dataset
FORCE_PROTOCOL = "ramp"
TEXTURE_PROTOCOL = "texture"
TEXTURE_SILENCE_US = 500_000  #: alignment: a PC spike after this much silence starts a texture window
SCAN_STEADY = 0.05  #: a scanning window's quarters each advance within 5 % of the window's mean


def to_us(t_s: np.ndarray) -> np.ndarray:
    """Seconds -> integer microseconds (rounded), int64."""
    return np.round(np.asarray(t_s, dtype=np.float64) * 1e6).astype(np.int64)


@dataclass
class EncodedTrial:
    """One trial's spikes (us, per class) with what labels need."""

    entry: dict[str, Any]
    spikes_us: dict[str, np.ndarray]
    st_t_us: np.ndarray
    st: np.ndarray
    end_us: int
    scan_t_us: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  #: scan position's times (us)
    scan_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))  #: lateral position of the surface (mm)

    @property
    def id(self) -> str:
        return str(self.entry["id"])

    @property
    def label(self) -> str:
        return str(self.entry.get("texture") or self.entry["condition"])


def encode(entry: dict[str, Any], trial: Trial, params: EncoderParams) -> EncodedTrial:
    spikes = encode_trial(trial, params)
    return EncodedTrial(entry, {c: to_us(t) for c, t in spikes.items()}, to_us(trial.st_t), np.asarray(trial.st, np.float64),
                        int(to_us(trial.duration_s)), *scan_track(entry, trial))


def scan_track(entry: dict[str, Any], trial: Trial) -> tuple[np.ndarray, np.ndarray]:
    """(times (us), lateral surface position (mm)) of a trial: its commanded ``cmd_x`` at ``cmd_fs``,
    else ``params.speed_mm_s`` from ``events.slide_start_s`` to ``slide_end_s`` (still before and
    after); empty when the recording states neither."""
    if trial.cmd_x is not None:
        t = trial.cmd_t0 + np.arange(trial.cmd_x.size) / trial.cmd_fs
        return to_us(t), np.asarray(trial.cmd_x, np.float64)
    speed = (entry.get("params") or {}).get("speed_mm_s")
    ev = entry.get("events") or {}
    if speed is None or "slide_start_s" not in ev or "slide_end_s" not in ev:
        return np.zeros(0, np.int64), np.zeros(0)
    t0, t1 = float(ev["slide_start_s"]), float(ev["slide_end_s"])
    return to_us(np.array([t0, t1])), np.array([0.0, float(speed) * (t1 - t0)])


def encode_entries(
    ds: Dataset, entries: Sequence[dict[str, Any]], params: EncoderParams, progress: Callable[[], None] | None = None
) -> list[EncodedTrial]:
    """Encode every entry with ``params`` (offline, one pass per trial)."""
    out = []
    for e in entries:
        out.append(encode(e, ds.load(e), params))
        if progress is not None:
            progress()
    return out


def split_entries(ds: Dataset, params: EncoderParams, protocol: str, split: str) -> tuple[list[dict[str, Any]], int]:
    """The entries of ``protocol`` in ``split`` (heldout | train | all) and the split seed used.

    The seed is the fit's (recorded in the parameters' provenance) when the parameters were fitted
    on this dataset, else :data:`DEFAULT_SPLIT_SEED`.
    """
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    entries = ds.entries(protocol)
    seed = params_split_seed(params, ds)
    seed = DEFAULT_SPLIT_SEED if seed is None else seed
    if split == "all":
        return entries, seed
    train, held = split_repeats(entries, seed)
    return (train if split == "train" else held), seed


def require_trials(ds: Dataset, protocol: str, what: str) -> None:
    if not ds.entries(protocol):
        raise RecordingError(f"{ds.root}: no {protocol} trials, needed for {what}")


# ------------------------------------------------------------------------------------- force
def force_steps(tr: EncodedTrial, window_us: int, step_us: int = F.STEP_US, from_start: bool = False) -> np.ndarray:
    """Decoding steps of a trial whose whole window lies inside the recording; ``from_start``: from
    the first step whose window starts at or after the recording's t = 0 instead of its first
    SingleTact sample (a stateful decoder's state then holds every spike of the recording)."""
    start = (0 if from_start else int(tr.st_t_us[0])) + window_us
    return F.step_times(start, min(tr.end_us, int(tr.st_t_us[-1])), step_us)


def force_label(tr: EncodedTrial, steps_us: np.ndarray, bin_us: int = F.BIN_US) -> np.ndarray:
    """Mean measured force (N) over the last bin ``[T - bin, T)`` of every step."""
    lo = np.searchsorted(tr.st_t_us, steps_us - bin_us, side="left")
    hi = np.searchsorted(tr.st_t_us, steps_us, side="left")
    csum = np.concatenate(([0.0], np.cumsum(tr.st)))
    n = hi - lo
    mean = (csum[hi] - csum[lo]) / np.maximum(n, 1)
    centre = np.interp(steps_us - bin_us / 2, tr.st_t_us, tr.st)
    return np.where(n > 0, mean, centre)


def force_windows(
    trials: Sequence[EncodedTrial], classes: Sequence[str], window_us: int, bin_us: int = F.BIN_US, step_us: int = F.STEP_US,
    from_start: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(counts (n, n_bins, n_classes), force (n,), trial index (n,), step (n,) us) over ``trials``;
    a trial's windows are contiguous and in step order."""
    xs, ys, gs, ts = [], [], [], []
    for i, tr in enumerate(trials):
        steps = force_steps(tr, window_us, step_us, from_start)
        xs.append(F.counts_tensor(tr.spikes_us, classes, steps, window_us, bin_us))
        ys.append(force_label(tr, steps, bin_us))
        gs.append(np.full(steps.size, i))
        ts.append(steps)
    nb = F.n_bins(window_us, bin_us)
    if not xs:
        return np.zeros((0, nb, len(classes)), np.float32), np.zeros(0), np.zeros(0, int), np.zeros(0, np.int64)
    return np.concatenate(xs), np.concatenate(ys), np.concatenate(gs), np.concatenate(ts)


# ----------------------------------------------------------------------------------- texture
def texture_windows(
    trials: Sequence[EncodedTrial],
    window_us: int,
    silence_us: int = TEXTURE_SILENCE_US,
    bin_us: int = F.BIN_US,
    step_us: int = F.STEP_US,
    classes: Sequence[str] = ("PC",),
) -> tuple[np.ndarray, list[str], np.ndarray, np.ndarray]:
    """(counts of ``classes`` (n, n_bins, n_classes), label per window, trial index (n,), step (n,) us)
    over ``trials``.

    The anchor is the trial's first PC spike, or a later one after ``silence_us`` without PC
    spikes (:func:`features.anchors`, as the streaming decoder does); windows end at most at the
    stimulus end.
    """
    xs, labels, gs, ts = [], [], [], []
    for i, tr in enumerate(trials):
        pc = tr.spikes_us["PC"]
        if pc.size == 0:
            continue
        stop = min(tr.end_us, int(to_us(tr.entry.get("stim_end_s", tr.end_us / 1e6))))
        steps = F.step_times(int(pc[0]) + 1, stop, step_us)
        ends, anchor = F.anchored_end(steps, F.anchors(pc, silence_us), bin_us)
        ok = F.ready(ends, anchor, window_us) & (ends <= stop)
        ends = ends[ok]
        xs.append(F.counts_tensor(tr.spikes_us, classes, ends, window_us, bin_us))
        labels += [tr.label] * ends.size
        gs.append(np.full(ends.size, i))
        ts.append(steps[ok])
    nb = F.n_bins(window_us, bin_us)
    if not xs:
        return np.zeros((0, nb, len(classes)), np.float32), [], np.zeros(0, int), np.zeros(0, np.int64)
    return np.concatenate(xs), labels, np.concatenate(gs), np.concatenate(ts)


def scan_windows(
    trials: Sequence[EncodedTrial],
    window_us: int,
    bin_us: int,
    classes: Sequence[str],
    step_us: int = F.STEP_US,
) -> tuple[np.ndarray, list[str], np.ndarray, np.ndarray, np.ndarray]:
    """(counts (n, n_bins, n_classes), label per window, trial index (n,), step (n,) us, scanning
    speed (n,) mm/s) of the windows ``[T - window, T)`` of ``trials`` during which the surface moves
    steadily (module docstring)."""
    xs, labels, gs, ts, vs = [], [], [], [], []
    for i, tr in enumerate(trials):
        if tr.scan_t_us.size < 2:
            continue
        steps = F.step_times(window_us, tr.end_us, step_us)
        edges = steps[:, None] - window_us + np.arange(5)[None, :] * (window_us / 4.0)
        x = np.interp(edges, tr.scan_t_us, tr.scan_mm)
        quarter = np.diff(x, axis=1)
        mean = (x[:, -1] - x[:, 0]) / 4.0
        ok = (mean > 0) & np.all(np.abs(quarter - mean[:, None]) <= SCAN_STEADY * mean[:, None], axis=1)
        steps = steps[ok]
        xs.append(F.counts_tensor(tr.spikes_us, classes, steps, window_us, bin_us))
        labels += [tr.label] * steps.size
        gs.append(np.full(steps.size, i))
        ts.append(steps)
        vs.append(4.0 * mean[ok] / (window_us / 1e6))
    if not xs:
        return np.zeros((0, F.n_bins(window_us, bin_us), len(classes)), np.float32), [], np.zeros(0, int), np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(xs), labels, np.concatenate(gs), np.concatenate(ts), np.concatenate(vs)
