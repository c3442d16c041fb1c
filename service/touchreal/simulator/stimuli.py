"""Stimulus generators of the rig protocols and the robot dynamics that execute them.

Pure computation, no I/O. A stimulus is an analytic commanded trajectory, evaluated at any times
``t`` (s) relative to its onset (the commanded start, ``onset_s`` in the manifest):

- :class:`RampHold`: robot probe indentation ramp-hold-release (depth mm, velocities mm/s, hold s).
- :class:`SineBurst`: exciter vibration burst (frequency Hz) with 50 ms linear on/off ramps, the
  probe resting on the skin with a static preload (mm); the exciter displacement (``drive_mm``) is
  set per frequency so that the PVDF amplitude is about equal across frequencies (paper, 2.2).
- :class:`TextureSlide`: comb pressed in, slid laterally (spacing mm, speed mm/s), lifted.

``depth`` is the robot depth command (mm, > 0 into the skin), ``x`` the lateral comb command
(mm), ``vibration`` the exciter displacement (mm) and ``nominal`` the TouchSim reference trace
(mm) stored as ``cmd_depth``. :class:`Robot` executes depth and x commands like a position
controlled arm: latency, finite bandwidth and an acceleration limit, so it cannot reach the
commanded velocity instantly, plus a short dwell before every reversal of the vertical motion.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numba
import numpy as np

from .eskin import FS_HZ, SkinParams, preload_depth_mm, vibration_drive_mm


@dataclass(frozen=True)
class RobotParams:
    """Robot arm dynamics (fitted to the rig-v1 ramp onsets, peaks and PVDF transients)."""

    latency_s: float = 0.0065  #: command -> motion latency (s)
    natural_hz: float = 16.8  #: bandwidth of the position loop (Hz)
    damping: float = 1.0  #: damping ratio of the position loop
    max_accel_mm_s2: float = 1900.0  #: acceleration limit (mm/s^2)
    reversal_dwell_s: float = 0.013  #: dwell before the vertical motion reverses (s)
    exciter_latency_s: float = 0.0  #: command -> exciter vibration latency (s) (0 on the rig-v1 build)


@numba.njit(cache=True, nogil=True)
def _track(cmd, state, wn, zeta, amax, dt):  # pragma: no cover - compiled
    # cmd (n, 2) depth and x commands (mm); state (2, 2) rows = axis, cols = (position, velocity)
    n = cmd.shape[0]
    out = np.empty_like(cmd)
    for k in range(n):
        for ax in range(2):
            x = state[ax, 0]
            v = state[ax, 1]
            a = wn * wn * (cmd[k, ax] - x) - 2.0 * zeta * wn * v
            if a > amax:
                a = amax
            elif a < -amax:
                a = -amax
            v += a * dt
            x += v * dt
            state[ax, 0] = x
            state[ax, 1] = v
            out[k, ax] = x
    return out


class Robot:
    """Stateful position tracking of (depth, x) commands at 2 kHz (mm).

    The latency is applied by evaluating the command ``latency_s`` earlier (see
    :func:`executed_command`); this class adds the position loop and the acceleration limit.
    """

    def __init__(self, params: RobotParams | None = None, depth_mm: float = 0.0, x_mm: float = 0.0) -> None:
        self.params = params or RobotParams()
        self._state = np.array([[depth_mm, 0.0], [x_mm, 0.0]], dtype=float)

    def track(self, depth_cmd_mm: np.ndarray, x_cmd_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Executed depth and x (mm) for the next ticks of commands."""
        p = self.params
        cmd = np.ascontiguousarray(np.stack([depth_cmd_mm, x_cmd_mm], axis=1), dtype=float)
        out = _track(cmd, self._state, 2 * np.pi * p.natural_hz, p.damping, p.max_accel_mm_s2, 1.0 / FS_HZ)
        return out[:, 0], out[:, 1]


def _ramp_profile(t: np.ndarray, depth: float, v_up: float, v_down: float, hold: float) -> np.ndarray:
    t = np.asarray(t, float)
    t_up = depth / v_up
    rel = t - t_up - hold
    d = np.where(t < t_up, v_up * t, np.where(rel < 0, depth, depth - v_down * rel))
    return np.where(t > 0, np.clip(d, 0.0, depth), 0.0)


class Stimulus:
    """Common interface of the protocol stimuli (times in s relative to the onset)."""

    protocol: ClassVar[str] = ""
    contactor: ClassVar[str] = "probe"  #: 'probe' (1 mm round probe) or 'comb'

    @property
    def duration_s(self) -> float:
        """Commanded onset -> commanded end (s)."""
        raise NotImplementedError

    @property
    def spacing_mm(self) -> float:
        return 0.0

    def events(self, onset_s: float) -> dict[str, float]:
        return {"onset_s": onset_s, "end_s": onset_s + self.duration_s}

    def depth(self, t: np.ndarray, dwell_s: float = 0.0) -> np.ndarray:
        """Robot depth command (mm); ``dwell_s`` delays reversals as the robot executes them."""
        return np.zeros(np.shape(t))

    def x(self, t: np.ndarray) -> np.ndarray:
        """Lateral comb command (mm)."""
        return np.zeros(np.shape(t))

    def vibration(self, t: np.ndarray) -> np.ndarray:
        """Exciter displacement (mm)."""
        return np.zeros(np.shape(t))

    def nominal(self, t: np.ndarray) -> np.ndarray:
        """TouchSim reference indentation (mm) = ``cmd_depth``."""
        return self.depth(t)

    def params(self) -> dict[str, float]:
        """Stimulus parameters as stored in the manifest."""
        raise NotImplementedError


@dataclass(frozen=True)
class RampHold(Stimulus):
    """Ramp from 0 to ``depth_mm`` at ``v_up_mm_s``, hold ``hold_s``, back to 0 at ``v_down_mm_s``."""

    depth_mm: float
    v_up_mm_s: float
    v_down_mm_s: float
    hold_s: float
    protocol: ClassVar[str] = "ramp"

    @property
    def duration_s(self) -> float:
        return self.depth_mm / self.v_up_mm_s + self.hold_s + self.depth_mm / self.v_down_mm_s

    def events(self, onset_s: float) -> dict[str, float]:
        hold = onset_s + self.depth_mm / self.v_up_mm_s
        return {"onset_s": onset_s, "hold_start_s": hold, "release_start_s": hold + self.hold_s, "end_s": onset_s + self.duration_s}

    def depth(self, t, dwell_s: float = 0.0):
        return _ramp_profile(t, self.depth_mm, self.v_up_mm_s, self.v_down_mm_s, self.hold_s + dwell_s)

    def params(self):
        return {"depth_mm": self.depth_mm, "v_up_mm_s": self.v_up_mm_s, "v_down_mm_s": self.v_down_mm_s, "hold_s": self.hold_s}


@dataclass(frozen=True)
class SineBurst(Stimulus):
    """Exciter burst of ``freq_hz`` lasting ``burst_s`` with ``ramp_s`` linear on/off ramps.

    ``drive_mm``: physical exciter displacement amplitude (mm); ``preload_mm``: static probe depth.
    ``resting=True`` (the rig's sine protocol): the probe rests at the preload for the whole
    recording and the burst starts at the onset. ``resting=False`` (live scenes): the robot presses
    to the preload at ``press_mm_s``, settles ``settle_s``, vibrates, settles and lifts.
    """

    freq_hz: float
    drive_mm: float
    preload_mm: float = 0.43
    burst_s: float = 1.0
    ramp_s: float = 0.05
    nominal_mm: float = 0.1
    resting: bool = True
    press_mm_s: float = 10.0
    settle_s: float = 0.2
    protocol: ClassVar[str] = "sine"

    @classmethod
    def calibrated(cls, freq_hz: float, skin: SkinParams | None = None, preload_n: float = 0.46, **kw) -> "SineBurst":
        """A burst whose drive gives the calibrated PVDF amplitude for a preload force of ``preload_n`` (N)."""
        skin = skin or SkinParams()
        pre = preload_depth_mm(preload_n, skin)
        return cls(freq_hz=float(freq_hz), drive_mm=vibration_drive_mm(freq_hz, pre, skin), preload_mm=pre, **kw)

    @property
    def _press_s(self) -> float:
        return 0.0 if self.resting else self.preload_mm / self.press_mm_s

    @property
    def burst_start(self) -> float:
        """Burst start relative to the onset (s)."""
        return 0.0 if self.resting else self._press_s + self.settle_s

    @property
    def duration_s(self) -> float:
        if self.resting:
            return self.burst_s
        return 2 * (self._press_s + self.settle_s) + self.burst_s

    def events(self, onset_s: float) -> dict[str, float]:
        ev = {"onset_s": onset_s, "end_s": onset_s + self.duration_s}
        if not self.resting:
            ev["burst_start_s"] = onset_s + self.burst_start
            ev["burst_end_s"] = onset_s + self.burst_start + self.burst_s
        return ev

    def _envelope_sine(self, t) -> np.ndarray:
        tb = np.asarray(t, float) - self.burst_start
        env = np.clip(np.minimum(tb, self.burst_s - tb) / self.ramp_s, 0.0, 1.0)
        return env * np.sin(2 * np.pi * self.freq_hz * tb)

    def depth(self, t, dwell_s: float = 0.0):
        if self.resting:
            return np.full(np.shape(t), self.preload_mm)
        hold = 2 * self.settle_s + self.burst_s
        return _ramp_profile(t, self.preload_mm, self.press_mm_s, self.press_mm_s, hold + dwell_s)

    def vibration(self, t):
        return self.drive_mm * self._envelope_sine(t)

    def nominal(self, t):
        return self.nominal_mm * self._envelope_sine(t)

    def params(self):
        return {"freq_hz": self.freq_hz}


@dataclass(frozen=True)
class TextureSlide(Stimulus):
    """Comb of tooth ``spacing`` (mm) pressed to ``depth_mm``, slid ``slide_s`` at ``speed_mm_s``, lifted."""

    spacing: float
    speed_mm_s: float = 30.0
    depth_mm: float = 0.5
    press_mm_s: float = 10.0
    dwell_s: float = 0.1
    slide_s: float = 2.0
    protocol: ClassVar[str] = "texture"
    contactor: ClassVar[str] = "comb"

    @property
    def spacing_mm(self) -> float:
        return self.spacing

    @property
    def _press_s(self) -> float:
        return self.depth_mm / self.press_mm_s

    @property
    def duration_s(self) -> float:
        return 2 * (self._press_s + self.dwell_s) + self.slide_s

    def events(self, onset_s: float) -> dict[str, float]:
        s0 = onset_s + self._press_s + self.dwell_s
        return {"onset_s": onset_s, "slide_start_s": s0, "slide_end_s": s0 + self.slide_s, "end_s": onset_s + self.duration_s}

    def depth(self, t, dwell_s: float = 0.0):
        return _ramp_profile(t, self.depth_mm, self.press_mm_s, self.press_mm_s, 2 * self.dwell_s + self.slide_s + dwell_s)

    def x(self, t):
        s0 = self._press_s + self.dwell_s
        return self.speed_mm_s * np.clip(np.asarray(t, float) - s0, 0.0, self.slide_s)

    def params(self):
        return {"spacing_mm": self.spacing, "speed_mm_s": self.speed_mm_s}


def executed_command(stim: Stimulus, t: np.ndarray, robot: RobotParams) -> tuple[np.ndarray, np.ndarray]:
    """Depth and x commands (mm) as the robot's controller sees them at times ``t`` (s, onset-relative).

    The robot starts ``latency_s`` late and dwells ``reversal_dwell_s`` before reversing.
    """
    tr = np.asarray(t, float) - robot.latency_s
    return stim.depth(tr, robot.reversal_dwell_s), stim.x(tr)

