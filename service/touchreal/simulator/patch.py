"""A patch of taxels under one probe: the raw recording of every taxel and the commanded indentation.

:func:`patch_skin` scales a build's spatial constants to taxels of a given pitch (a skin tiled with
sensors as wide as their pitch: the rig's SingleTact is 8 mm wide, so a 3 mm pitch has sensors
3/8 its size, same physics); :func:`probe_recording` plays one stimulus at a probe position
over the patch, as ``simulate_trial`` does for one taxel, and returns the commanded trace the
TouchSim reference is computed from.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..raw import RawChunk
from .eskin import SkinParams
from .scene import Scene, SceneEvent, SceneSource
from .stimuli import Stimulus

RIG_SENSOR_MM = 8.0  #: width of the rig's SingleTact, the pitch the build's spatial constants describe
CMD_FS_HZ = 5000.0  #: rate of the commanded trace (the reference model's rate)


def patch_skin(pitch_mm: float, skin: SkinParams | None = None) -> SkinParams:
    """The build ``skin`` (default the rig's) with its sensors' extents (the SingleTact's and the film's
    edges) scaled to sensors ``pitch_mm`` wide, centred on their taxel (the rig sensor's centre offsets
    and axis ratios removed). How vibration decays through the silicone (``pv_decay_mm``,
    ``pv_spread_decay_mm``) is the skin's, not the sensor's, and is kept."""
    s = skin or SkinParams()
    k = pitch_mm / RIG_SENSOR_MM
    return replace(s, st_edge_mm=s.st_edge_mm * k, st_edge_width_mm=s.st_edge_width_mm * k, st_center_mm=(0.0, 0.0),
                   st_axis_ratio=1.0, pv_edge_mm=s.pv_edge_mm * k, pv_edge_width_mm=s.pv_edge_width_mm * k,
                   pv_center_mm=(0.0, 0.0), pv_axis_ratio=1.0)


def grid_patch(side: int, pitch_mm: float) -> np.ndarray:
    """(side^2, 2) taxel centres (mm) of a square grid centred on (0, 0), row-major from (-, -)."""
    u = (np.arange(side) - (side - 1) / 2.0) * pitch_mm
    return np.stack(np.meshgrid(u, u), axis=-1).reshape(-1, 2)


@dataclass(frozen=True)
class ProbeRecording:
    raw: RawChunk  #: every taxel's samples (s on the recording clock)
    cmd_depth: np.ndarray  #: (T,) commanded indentation (mm) at CMD_FS_HZ from t = 0
    onset_s: float


def probe_recording(stim: Stimulus, probe_xy_mm: tuple[float, float], taxels_xy_mm: np.ndarray, *, skin: SkinParams,
                    onset_s: float = 0.3, tail_s: float = 0.4, seed: int = 0) -> ProbeRecording:
    """Play ``stim`` at ``probe_xy_mm`` over the taxels; the recording runs ``tail_s`` past its end."""
    duration = math.ceil((onset_s + stim.duration_s + tail_s) * 100.0) / 100.0
    src = SceneSource(Scene((SceneEvent(onset_s, stim, tuple(probe_xy_mm)),)), taxels_xy_mm=taxels_xy_mm, seed=seed,
                      skin=skin, t0_s=0.0, st_phase_ticks=0)
    raw = src.read(duration)
    t = np.arange(int(round(duration * CMD_FS_HZ))) / CMD_FS_HZ - onset_s
    return ProbeRecording(raw, stim.nominal(t).astype(np.float64), onset_s)
