"""A stand-in for the microcontroller: plays recordings as serial frames through a pseudo-terminal.

:func:`frame_schedule` (sans-I/O) turns trials into the frames the MCU would send, each with the
device time (us) it goes out: trials back to back on one continuous device clock, one SingleTact
frame per ``st_block`` samples (10 ms each) and one PVDF frame per ``pvdf_block`` samples (0.5 ms
each), a frame sent when its last sample is taken. Faults are drawn from a seeded generator:
dropped frames (their sequence numbers are used up, as when the MCU's buffer overflows) and
corrupted frames (one byte flipped). :class:`Link` and :func:`departures` (sans-I/O) add a device
clock that drifts against the host's and a USB link that delays frames at random and stalls now
and then; the true acquisition instants are reported so a host's clock estimate can be checked.

:class:`PtyPort` is the thin I/O layer: a pty pair whose slave is reachable through a symlink
(like a udev ``/dev/ttyACM0`` link). As a USB CDC device only transmits while the host holds the
port open, frames are written only while a reader has the slave open (the master reports POLLHUP
otherwise); :func:`play` paces the schedule in real time (or ``speed`` times faster) and can
unplug (close the pty, remove the link) and replug (new pty, new link) periodically.
"""

from __future__ import annotations

import heapq
import math
import os
import select
import time
import tty
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..recording import Trial
from .serial_frame import PERIOD_US, Channel, encode_frame


HOST_SETTLE_S = 0.1  #: pause after a host opens the port before playback starts (wait_for_host_s)
STALLS_PER_S = 1.0  #: mean rate of link stalls (Poisson, host time) when there is jitter
STALL_JITTERS = 10.0  #: a stall lasts this many mean jitters


@dataclass(frozen=True)
class Faults:
    """Per-frame fault probabilities and the generator seed."""

    drop_rate: float = 0.0
    corrupt_rate: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("drop_rate", "corrupt_rate"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")


@dataclass(frozen=True)
class Link:
    """The device clock against the host's and the delays of the link.

    The device clock runs ``drift_ppm`` fast (negative: slow): a device second lasts
    1 / (1 + drift_ppm 1e-6) host seconds. Each frame leaves ``jitter_ms`` late on average
    (exponential), and about STALLS_PER_S times a second the link stalls for STALL_JITTERS x
    ``jitter_ms``: frames acquired meanwhile leave together when it ends. Frames leave in order.
    """

    drift_ppm: float = 0.0
    jitter_ms: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        if not -10_000 <= self.drift_ppm <= 10_000:
            raise ValueError(f"drift_ppm must be in [-10000, 10000], got {self.drift_ppm}")
        if not 0.0 <= self.jitter_ms <= 1000.0:
            raise ValueError(f"jitter_ms must be in [0, 1000], got {self.jitter_ms}")


def departures(
    schedule: Iterable[tuple[int, bytes]], link: Link = Link(), speed: float = 1.0
) -> Iterator[tuple[int, float, float, bytes]]:
    """(device us of the frame's newest sample, host s it was acquired, host s it leaves, frame) for
    ``schedule``; host times count from the first frame's acquisition, ``speed`` x real time."""
    rng = np.random.default_rng((link.seed, 1))
    scale = 1e-6 / speed / (1.0 + link.drift_ppm * 1e-6)
    jitter_s = link.jitter_ms / 1e3
    stall_s = STALL_JITTERS * jitter_s
    first_us: int | None = None
    stall_at = float(rng.exponential(1 / STALLS_PER_S)) if jitter_s > 0 else math.inf
    leave = 0.0
    for device_us, data in schedule:
        first_us = device_us if first_us is None else first_us
        acquired = (device_us - first_us) * scale
        while stall_at + stall_s <= acquired:
            stall_at += stall_s + float(rng.exponential(1 / STALLS_PER_S))
        leave = max(leave, acquired + (float(rng.exponential(jitter_s)) if jitter_s > 0 else 0.0))
        if stall_at <= acquired:
            leave = max(leave, stall_at + stall_s)
        yield device_us, acquired, leave, data


def _channel_frames(
    channel: Channel, t_s: np.ndarray, x: np.ndarray, offset_us: int, block: int
) -> Iterator[tuple[int, Channel, int, np.ndarray]]:
    """(send_us, channel, t0_us, samples) blocks of one channel; a block never spans a timing gap."""
    period = PERIOD_US[channel]
    t_us = offset_us + np.rint(np.asarray(t_s) * 1e6).astype(np.int64)
    i, n = 0, t_us.size
    while i < n:
        j = min(i + block, n)
        off_grid = np.abs(t_us[i:j] - (t_us[i] + period * np.arange(j - i))) > period // 2
        if off_grid.any():
            j = i + int(np.argmax(off_grid))
        yield int(t_us[j - 1]), channel, int(t_us[i]), x[i:j]
        i = j


def frame_schedule(
    trials: Iterable[Trial],
    n_taxels: int = 1,
    st_block: int = 1,
    pvdf_block: int = 10,
    faults: Faults = Faults(),
) -> Iterator[tuple[int, bytes]]:
    """(send time in device us, frame bytes) for ``trials`` played back to back.

    Each trial's recording clock is shifted onto the device clock by a whole number of SingleTact
    periods past the end of the previous trial, so both sensors keep their sample phase. Every
    taxel carries the trial's (single-taxel) samples. ``trials`` may be endless (looping).
    """
    rng = np.random.default_rng(faults.seed)
    session = int(rng.integers(0, 1 << 16))
    seq = {Channel.SINGLETACT: 0, Channel.PVDF: 0}
    offset_us = 0
    st_period = PERIOD_US[Channel.SINGLETACT]
    for trial in trials:
        st = np.repeat(np.asarray(trial.st, np.float32)[:, None], n_taxels, axis=1)
        pv = np.repeat(np.asarray(trial.pvdf, np.float32)[:, None], n_taxels, axis=1)
        blocks = heapq.merge(
            _channel_frames(Channel.SINGLETACT, trial.st_t, st, offset_us, st_block),
            _channel_frames(Channel.PVDF, trial.pvdf_t, pv, offset_us, pvdf_block),
            key=lambda b: (b[0], b[1]),
        )
        for send_us, channel, t0_us, samples in blocks:
            frame_seq = seq[channel]
            seq[channel] += 1
            if rng.random() < faults.drop_rate:
                continue
            data = bytearray(encode_frame(channel, frame_seq, session, t0_us, samples))
            if rng.random() < faults.corrupt_rate:
                data[int(rng.integers(len(data)))] ^= int(rng.integers(1, 256))
            yield send_us, bytes(data)
        end_us = offset_us + int(np.rint(trial.duration_s * 1e6))
        offset_us = math.ceil((end_us + st_period) / st_period) * st_period


@dataclass
class PortStats:
    """What the emulated device did with its frames."""

    frames_written: int = 0
    frames_unread: int = 0  #: produced while no host had the port open (or unplugged)
    bytes_written: int = 0
    bytes_dropped: int = 0  #: the host did not read in time (pty buffer full)
    plugs: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class PtyPort:
    """The MCU's end of a pseudo-terminal; the host opens the slave through the symlink ``path``."""

    def __init__(self, path: str | Path, write_timeout_s: float = 0.25):
        self.path = Path(path)
        self.write_timeout_s = write_timeout_s
        self.stats = PortStats()
        self._master: int | None = None
        self._poll = select.poll()
        self._stalled = False  # the last write timed out: do not wait again until one succeeds
        if self.path.exists() and not self.path.is_symlink():
            raise ValueError(f"{self.path} exists and is not a symlink: refusing to replace it")

    @property
    def plugged(self) -> bool:
        return self._master is not None

    def plug(self) -> None:
        """Create a new pty pair and point the link at its slave."""
        if self._master is not None:
            return
        master, slave = os.openpty()
        tty.setraw(slave)  # binary clean before any host configures it
        slave_name = os.ttyname(slave)
        os.close(slave)  # the master reports POLLHUP until a host opens the slave
        os.set_blocking(master, False)
        tmp = self.path.with_name(self.path.name + ".tmp")
        tmp.unlink(missing_ok=True)
        os.symlink(slave_name, tmp)
        os.replace(tmp, self.path)
        self._master = master
        self._poll = select.poll()
        self._poll.register(master, select.POLLOUT)
        self._stalled = False
        self.stats.plugs += 1

    def unplug(self) -> None:
        """Remove the link and close the pty: a host reading the slave gets an I/O error."""
        if self._master is None:
            return
        self.path.unlink(missing_ok=True)
        os.close(self._master)
        self._master = None

    def host_attached(self) -> bool:
        """Whether a host has the port open (the master does not report a hang-up)."""
        if self._master is None:
            return False
        return not any(ev & select.POLLHUP for _, ev in self._poll.poll(0))

    def send(self, data: bytes) -> None:
        """Write one frame if a host is attached; what does not fit in time is dropped."""
        if not self.host_attached():
            self.stats.frames_unread += 1
            return
        assert self._master is not None
        view = memoryview(data)
        deadline = time.monotonic() + (0.0 if self._stalled else self.write_timeout_s)
        while view:
            try:
                view = view[os.write(self._master, view) :]
            except BlockingIOError:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not self._poll.poll(remaining * 1000):
                    break
            except OSError:  # the host closed the port meanwhile
                break
        self._stalled = bool(view)
        self.stats.bytes_written += len(data) - len(view)
        self.stats.bytes_dropped += len(view)
        self.stats.frames_written += not view

    def close(self) -> None:
        self.unplug()


def play(
    schedule: Iterable[tuple[int, bytes]],
    port: PtyPort,
    speed: float = 1.0,
    unplug_after_s: float | None = None,
    replug_after_s: float = 1.0,
    wait_for_host_s: float = 0.0,
    linger_s: float = 0.5,
    should_stop: Callable[[], bool] = lambda: False,
    link: Link = Link(),
    on_acquired: Callable[[int, float], None] = lambda device_us, mono_s: None,
) -> PortStats:
    """Send ``schedule`` through ``port`` paced at ``speed`` x real time, through ``link``
    (:func:`departures`); ``on_acquired(device_us, mono_s)`` is told, per frame, the host monotonic
    time (s) at which its newest sample was acquired.

    With ``unplug_after_s`` the port is unplugged after that many seconds of playback (recording
    time) and replugged ``replug_after_s`` later, repeatedly; the device clock and sequence numbers
    run on meanwhile. ``wait_for_host_s`` holds the start until a host opens the port (like firmware
    that waits for the USB host), at most that long, then ``HOST_SETTLE_S`` more for the host to
    configure the port (opening flushes its input: frames written meanwhile would be lost). After the last frame the port stays open
    ``linger_s`` (wall time) so the host can read what is still in the pty's buffer.
    """
    if speed <= 0:
        raise ValueError("speed must be positive")
    port.plug()
    if wait_for_host_s > 0:
        _wait(wait_for_host_s, lambda: port.host_attached() or should_stop())
        time.sleep(HOST_SETTLE_S)
    start = time.monotonic()
    first_us: int | None = None
    for send_us, acquired_s, leave_s, data in departures(schedule, link, speed):
        if should_stop():
            break
        first_us = send_us if first_us is None else first_us
        rec_s = (send_us - first_us) / 1e6
        on_acquired(send_us, start + acquired_s)
        delay = start + leave_s - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        if unplug_after_s is not None:
            connected = rec_s % (unplug_after_s + replug_after_s) < unplug_after_s
            if connected and not port.plugged:
                port.plug()
            elif not connected and port.plugged:
                port.unplug()
        if port.plugged:
            port.send(data)
        else:
            port.stats.frames_unread += 1
    _wait(linger_s, should_stop)
    return port.stats


def _wait(timeout_s: float, done: Callable[[], bool]) -> None:
    """Poll ``done`` every 5 ms for at most ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not done() and time.monotonic() < deadline:
        time.sleep(0.005)
