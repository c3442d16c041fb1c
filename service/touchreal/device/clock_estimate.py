"""Sans-I/O estimate of a device clock against host receive times (offset and drift).

The host sees, for each serial frame, the device time ``x`` (us) of its newest sample and the
host time ``h`` (us) at which the frame arrived. A frame can only arrive *after* its sample was
taken: ``h = A(x) + d`` with ``A`` the affine map device -> host acquisition time (offset and
drift, rate ``A'`` near 1) and a receive delay ``d >= 0`` (USB polling, scheduling, bursts). So the
frames that arrived fastest trace ``A`` from above, and a lower-envelope fit recovers it:

1. Device time is cut into windows of ``window_us``; each window keeps only the pair with the
   smallest ``h - x`` (one point per window, at most ``horizon_us / window_us`` points: bounded
   memory, O(1) per frame). The fit uses the complete windows (a window just begun has seen too
   few frames for its minimum to mean much).
2. The lower convex hull of those minima gives a first line under all of them (the edge spanning
   their mean ``x``, i.e. the line minimising the total height of the points above it); minima
   more than ``max(3 x median height, OUTLIER_FLOOR_US)`` above it are stalls, dropped.
3. A least-squares line through the remaining minima gives the rate; it is lowered until it
   touches the lowest of them (the envelope), which gives the offset.

The stated error (``error_us``) at device time ``x`` is ``FLOOR_US`` + the median height of the
minima above the line + 3 x (their scatter + the slope's standard error x the distance from the
touching point). It does not include the fixed minimum transport delay (the fastest frame's
delay), which is indistinguishable from the offset. Settling and bounds: docs/serial-protocol.md.

``epoch`` counts mapping jumps: :meth:`DeviceClock.reset` (device restart: new clock, points
forgotten) and :meth:`DeviceClock.mark_jump` (reconnect: same clock, announced anew). A device time
running backwards by more than ``window_us`` or a window minimum far *below* the current line
(which no delay can explain: the device clock jumped) resets the estimate by itself.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

WINDOW_US = 250_000  #: one minimum per 0.25 s of device time
HORIZON_US = 60_000_000  #: fit over the last 60 s of device time
FLOOR_US = 100  #: error floor: host read granularity and unmodelled clock wander (us)
SIGMA_FLOOR_US = 20.0  #: smallest scatter assumed for the window minima (us)
OUTLIER_FLOOR_US = 200.0  #: minima this close to the envelope are never treated as bursts (us)
JUMP_US = 50_000  #: a window minimum this far below the line (beyond its error) is a clock jump (us)
PROVISIONAL_PPM = 1000.0  #: rate uncertainty assumed before two windows are complete (ppm)


@dataclass(frozen=True)
class ClockEstimate:
    """The device sample stamped ``device_us`` was acquired at host time ``host_us`` +- ``error_us``;
    nearby, host(t) = host_us + (t - device_us) * rate (host us per device us)."""

    device_us: int
    host_us: int
    rate: float
    error_us: int
    epoch: int


@dataclass(frozen=True)
class _Line:
    """host - device = a + b * (device - x_ref) near the points it was fitted to."""

    x_ref: int
    a: float
    b: float
    x_touch: float  #: device time (relative to x_ref) where the line touches the envelope
    sigma_us: float  #: scatter of the minima about the line
    slope_sd: float  #: standard error of b
    height_us: float  #: median height of the minima above the line

    def at(self, device_us: int) -> tuple[float, float]:
        """(host - device, stated error) at ``device_us``, us."""
        dx = device_us - self.x_ref
        err = FLOOR_US + self.height_us + 3.0 * (self.sigma_us + self.slope_sd * abs(dx - self.x_touch))
        return self.a + self.b * dx, err


class DeviceClock:
    """Fed ``add(device_us, host_us)`` per frame; ``estimate(device_us)`` maps device time to host
    time (the same clock as ``host_us``, us): ``None`` before the first frame, provisional (rate 1,
    the fastest frame's arrival, error = the spread of arrival lags + PROVISIONAL_PPM of the distance)
    until two windows are complete."""

    def __init__(self, window_us: int = WINDOW_US, horizon_us: int = HORIZON_US):
        if window_us <= 0 or horizon_us < 2 * window_us:
            raise ValueError("window_us must be positive and horizon_us at least two windows")
        self.window_us = int(window_us)
        self.n_windows = int(horizon_us // window_us)
        self.epoch = 0
        self.resets = 0  #: estimates dropped because the device clock jumped
        self._minima: deque[list[int]] = deque()  # [window index, device_us, host_us - device_us]
        self._newest_us: int | None = None
        self._max_lag = 0  # largest host - device seen this epoch (the provisional error)
        self._line: _Line | None = None
        self._stale = False

    def reset(self) -> None:
        """The device clock restarted: forget every point, start a new epoch."""
        self._minima.clear()
        self._newest_us = None
        self._max_lag = 0
        self._line = None
        self._stale = False
        self.epoch += 1

    def mark_jump(self) -> None:
        """Announce a new epoch (a reconnect) while keeping the fit: the device clock ran on."""
        self.epoch += 1

    def add(self, device_us: int, host_us: int) -> None:
        """One frame: device time of its newest sample and host time of its arrival (both us)."""
        device_us, lag = int(device_us), int(host_us) - int(device_us)
        if self._newest_us is not None and device_us < self._newest_us - self.window_us:
            self._jumped()
        self._max_lag = lag if self._newest_us is None else max(self._max_lag, lag)
        self._newest_us = device_us if self._newest_us is None else max(self._newest_us, device_us)
        k = device_us // self.window_us
        if self._minima and k <= self._minima[-1][0]:  # same window (or a late frame): keep the lowest
            last = self._minima[-1]
            if lag < last[2]:  # the open window is not in the fit: nothing to refit
                last[1], last[2] = device_us, lag
            return
        if self._minima:  # the previous window is complete: is it consistent with the rest?
            self._check_jump()
        while self._minima and self._minima[0][0] <= k - self.n_windows:
            self._minima.popleft()
        self._minima.append([k, device_us, lag])
        self._stale = True

    def estimate(self, device_us: int) -> ClockEstimate | None:
        """Host time (us, the clock of ``host_us``) at which device time ``device_us`` was sampled."""
        if not self._minima:
            return None
        line = self._fit()
        if line is None:
            _, x, lag = min(self._minima, key=lambda m: m[2])
            err = FLOOR_US + self._max_lag - lag + PROVISIONAL_PPM * 1e-6 * abs(device_us - x)
            return ClockEstimate(int(device_us), int(device_us) + lag, 1.0, int(np.ceil(err)), self.epoch)
        lag, err = line.at(device_us)
        return ClockEstimate(int(device_us), int(round(device_us + lag)), 1.0 + line.b, int(np.ceil(err)), self.epoch)

    def _jumped(self) -> None:
        self.resets += 1
        self.reset()

    def _check_jump(self) -> None:
        """Reset if the last complete window's minimum lies far below the line of the others."""
        if len(self._minima) < 4:
            return
        line = self._fit()  # the complete windows but the last
        _, x, lag = self._minima[-1]
        if line is not None:
            want, err = line.at(x)
            if lag < want - err - JUMP_US:
                self._jumped()

    def _fit(self) -> _Line | None:
        if not self._stale:
            return self._line
        self._stale = False
        self._line = None
        if len(self._minima) < 3:
            return None
        pts = np.array([(m[1], m[2]) for m in list(self._minima)[:-1]], dtype=np.int64)  # complete windows
        x_ref = int(pts[0, 0])
        x = (pts[:, 0] - x_ref).astype(np.float64)
        y = pts[:, 1].astype(np.float64)
        if np.ptp(x) <= 0:
            return None
        b0, a0 = _envelope(x, y)
        height = y - (a0 + b0 * x)
        keep = height <= max(3.0 * float(np.median(height)), OUTLIER_FLOOR_US)
        xs, ys = x[keep], y[keep]
        if xs.size < 2 or np.ptp(xs) <= 0:
            xs, ys = x, y
        b, _ = np.polyfit(xs, ys, 1)
        a_all = ys - b * xs
        touch = int(np.argmin(a_all))
        a = float(a_all[touch])
        resid = ys - (a + b * xs)
        sxx = float(np.sum((xs - xs.mean()) ** 2))
        scatter = float(np.std(resid, ddof=2)) if xs.size > 2 else 0.0
        sigma = max(scatter, SIGMA_FLOOR_US)
        self._line = _Line(x_ref, a, float(b), float(xs[touch]), sigma, sigma / np.sqrt(sxx), float(np.median(resid)))
        return self._line


def _envelope(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(slope, intercept) of the lower-hull edge over mean(x): the line under every point that
    minimises their total height above it. ``x`` must not be all equal."""
    order = np.lexsort((y, x))
    hull: list[int] = []
    for i in order:
        if hull and x[hull[-1]] == x[i]:
            continue  # same x, higher y (lexsort): never on the lower hull
        while len(hull) >= 2:
            o, p = hull[-2], hull[-1]
            if (x[p] - x[o]) * (y[i] - y[o]) - (y[p] - y[o]) * (x[i] - x[o]) <= 0:
                hull.pop()  # p is not below the chord o -> i
            else:
                break
        hull.append(int(i))
    xm = float(x.mean())
    for p, q in zip(hull, hull[1:]):
        if x[q] >= xm:
            break
    slope = float((y[q] - y[p]) / (x[q] - x[p]))
    return slope, float(y[p] - slope * x[p])
