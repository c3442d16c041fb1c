"""Live source reading the microcontroller over a serial port (pyserial), reconnecting on unplug.

A reader thread opens the port, feeds a :class:`~touchreal.device.serial_frame.FrameParser` and
collects the decoded samples; :meth:`SerialSource.next_chunk` hands them out once per update
interval (default 32 ms) as a :class:`~touchreal.raw.RawChunk` on the sensor clock
(s = device us / 1e6). On a read error or unplug the thread closes the port and retries with
exponential backoff (0.1 s doubling to 2 s); the samples lost meanwhile are simply absent and the
preprocessing's ``Sanitizer`` interpolates and counts the gap. Nothing here raises for device
trouble: it is visible in :meth:`SerialSource.status`.

Values are passed through unchanged, NaN and Inf included: the ``Sanitizer`` holds the last good
value and counts them (docs/architecture.md, input policy).

The device clock is mapped onto the host's by a :class:`~touchreal.device.clock_estimate.DeviceClock`
fed every frame's newest sample time and its arrival on the host's monotonic clock;
:meth:`SerialSource.clock` states it on the wall clock (docs/serial-protocol.md, host clock).
"""

from __future__ import annotations

import errno
import fcntl
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable

import numpy as np
import serial
from touchreal_client.clock import ClockPoint

from .clock_estimate import ClockEstimate, DeviceClock
from ..raw import RawChunk, taxel_grid
from .serial_frame import MAX_TAXELS, PERIOD_US, Channel, Event, Frame, FrameParser, Restart

DEFAULT_BAUDRATE = 921_600
BACKOFF_S = (0.1, 2.0)  #: first and largest reconnect delay
READ_TIMEOUT_S = 0.05  #: longest a blocking read waits (bounds how fast close() is noticed)
MAX_PENDING_S = 10.0  #: samples kept for a consumer that stopped calling next_chunk (s per channel)
MAX_SENSOR_US = 1 << 62  #: sensor times must stay below this (146 000 years; int64 arithmetic downstream)
WALL_STEP_US = 1000  #: wall - monotonic moving by more than this is a step of the wall clock (a new epoch)


class SampleCollector:
    """Sans-I/O: parser events -> pending samples on the sensor clock, per channel.

    Frames with another taxel count than ``n_taxels`` are rejected and counted
    (``wrong_taxels``), as are frames whose times fall outside 0 .. MAX_SENSOR_US on the sensor
    clock (``bad_times``: a device clock gone wild). After a device restart (:class:`Restart`: its
    clock starts again at 0) the device clock is re-based so the new samples continue after the
    last delivered ones, spaced by the host time that passed (``now_s``), so sensor time never runs
    backwards, and :attr:`device_clock` (sensor clock -> host time of acquisition) starts a new
    epoch. If nobody takes the samples, at most ``MAX_PENDING_S`` of each channel are kept; older
    frames are dropped and counted (``overflowed``), so a stalled consumer cannot exhaust memory.
    """

    def __init__(self, n_taxels: int):
        self.n_taxels = n_taxels
        self.wrong_taxels = 0
        self.bad_times = 0
        self.overflowed = 0
        self.samples = {Channel.SINGLETACT: 0, Channel.PVDF: 0}
        self._offset_us = 0  # sensor clock = device clock + offset
        self._rebase = False
        self.device_clock = DeviceClock()  #: sensor clock -> host monotonic time of acquisition (us)
        self.last_us: int | None = None  #: sensor time of the latest sample delivered (us)
        self._last_host_s = 0.0  # host time it arrived
        self._pending: dict[Channel, deque[tuple[np.ndarray, np.ndarray]]] = {c: deque() for c in Channel}
        self._n_pending = {c: 0 for c in Channel}

    def add(self, events: Iterable[Event], now_s: float) -> None:
        """Take the frames of ``events``; ``now_s`` is the host's monotonic time of arrival (s)."""
        for ev in events:
            if isinstance(ev, Restart):
                self._rebase = self.last_us is not None
                self.device_clock.reset()
            elif isinstance(ev, Frame):
                if ev.samples.shape[1] != self.n_taxels:
                    self.wrong_taxels += 1
                    continue
                if self._rebase:
                    elapsed_us = max(round((now_s - self._last_host_s) * 1e6), PERIOD_US[ev.channel])
                    self._offset_us = self.last_us + elapsed_us - ev.t0_us
                    self._rebase = False
                first_us = ev.t0_us + self._offset_us
                if first_us < 0 or first_us + PERIOD_US[ev.channel] * ev.samples.shape[0] >= MAX_SENSOR_US:
                    self.bad_times += 1
                    continue
                t_us = first_us + PERIOD_US[ev.channel] * np.arange(ev.samples.shape[0], dtype=np.int64)
                self._keep(ev.channel, t_us, ev.samples)
                self.samples[ev.channel] += ev.samples.shape[0]
                self.device_clock.add(int(t_us[-1]), round(now_s * 1e6))
                self.last_us = max(int(t_us[-1]), self.last_us if self.last_us is not None else int(t_us[-1]))
                self._last_host_s = now_s

    def _keep(self, channel: Channel, t_us: np.ndarray, samples: np.ndarray) -> None:
        pending = self._pending[channel]
        pending.append((t_us, samples))
        self._n_pending[channel] += t_us.size
        limit = MAX_PENDING_S * 1e6 / PERIOD_US[channel]
        while self._n_pending[channel] > limit:
            self._n_pending[channel] -= pending.popleft()[0].size
            self.overflowed += 1

    def take(self) -> RawChunk:
        """Every sample collected since the last call (times in s, values float64)."""
        parts = []
        for ch in (Channel.SINGLETACT, Channel.PVDF):
            got = self._pending[ch]
            self._pending[ch], self._n_pending[ch] = deque(), 0
            t = np.concatenate([g[0] for g in got]) / 1e6 if got else np.zeros(0)
            x = np.concatenate([g[1] for g in got]).astype(np.float64) if got else np.zeros((0, self.n_taxels))
            parts += [t, x]
        return RawChunk(*parts)


def check_device(port: str) -> None:
    """Raise ValueError, saying why, unless ``port`` is a serial device this process could open now:
    it exists, is a terminal (a TTY; ``/dev/null`` or a file is not) and nobody holds it exclusively
    (pyserial's ``exclusive=True`` lock, or ``TIOCEXCL``)."""
    try:
        fd = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except FileNotFoundError:
        raise ValueError(f"serial device {port} not found") from None
    except OSError as exc:
        if exc.errno == errno.EBUSY:
            raise ValueError(f"serial device {port} is busy (another program holds it exclusively)") from None
        raise ValueError(f"serial device {port} cannot be opened: {exc.strerror}") from None
    try:
        if not os.isatty(fd):
            raise ValueError(f"{port} is not a serial device (not a terminal)")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ValueError(f"serial device {port} is busy (another program has it open)") from None
        fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


class SerialSource:
    """The live-source interface over a serial port: ``next_chunk()``, ``status()``, ``close()``.

    ``port`` is a device path, or with ``allow_urls`` any pyserial URL (``serial_for_url``: ``spy://``,
    ``socket://``... reach files and hosts, so they are off unless asked for); ``update_s`` is how long
    :meth:`next_chunk` blocks (s). Taxel centres are ``taxel_grid(n_taxels)`` (mm).
    """

    segment = 0  #: one stream, reconnects included (a gap, not a new segment)
    offset_us = 0  #: the device clock is the wire clock

    def __init__(
        self,
        port: str,
        n_taxels: int = 1,
        update_s: float = 0.032,
        baudrate: int = DEFAULT_BAUDRATE,
        backoff_s: tuple[float, float] = BACKOFF_S,
        allow_urls: bool = True,
        wall_ns: Callable[[], int] = time.time_ns,
    ):
        if update_s <= 0:
            raise ValueError("update_s must be positive")
        if not 1 <= n_taxels <= MAX_TAXELS:
            raise ValueError(f"n_taxels must be in 1..{MAX_TAXELS}, got {n_taxels}")
        if not allow_urls and "://" in port:
            raise ValueError("serial port must be a device path (pyserial URLs are off)")
        self.port = port
        self._open = serial.serial_for_url if allow_urls else serial.Serial
        self.n_taxels = int(n_taxels)
        self.positions_mm = taxel_grid(self.n_taxels)
        self.update_s = float(update_s)
        self.baudrate = int(baudrate)
        self.backoff_s = backoff_s
        self._parser = FrameParser()
        self._collector = SampleCollector(self.n_taxels)
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._state = "connecting"
        self._connects = 0
        self._bytes = 0
        self._last_error = ""
        self._last_frame_s: float | None = None  # host monotonic time of the latest valid frame
        self._wall_ns = wall_ns
        self._wall_minus_mono_us: int | None = None
        self._wall_steps = 0
        self._next_tick = time.monotonic() + self.update_s
        self._thread = threading.Thread(target=self._run, name=f"serial-source {port}", daemon=True)
        self._thread.start()

    def next_chunk(self) -> RawChunk | None:
        """Wait until the next update tick and return the samples that arrived (possibly none)."""
        now = time.monotonic()
        if self._next_tick < now - self.update_s:  # fell behind by over a tick: do not burst
            self._next_tick = now
        if self._closed.wait(max(0.0, self._next_tick - now)):
            return None
        self._next_tick += self.update_s
        with self._lock:
            return self._collector.take()

    def clock(self) -> ClockPoint | None:
        """The clock model at the newest sample received: its sensor time (the re-based device
        clock, us), the wall time (Unix, us, from ``wall_ns``) it was acquired, estimated from the
        host's monotonic arrival times (docs/serial-protocol.md) and moved onto the wall clock by
        the current wall - monotonic difference (both run at the system clock's rate, so it only
        changes when the wall clock is stepped); rate = wall us per device us; epoch + 1 on a device
        restart, a reconnect or a step of the wall clock. None before the first frame."""
        mono0 = time.monotonic_ns()
        wall = self._wall_ns()
        mono1 = time.monotonic_ns()
        offset = (wall - (mono0 + mono1) // 2) // 1000
        clean = mono1 - mono0 < WALL_STEP_US * 500  # ns: not preempted between the readings
        with self._lock:
            est = self._estimate()
            known = self._wall_minus_mono_us
            if known is not None and clean and abs(offset - known) > WALL_STEP_US:
                self._wall_steps += 1
                known = None
            if known is None:
                self._wall_minus_mono_us = known = offset
            steps = self._wall_steps
        if est is None:
            return None
        return ClockPoint(est.device_us, est.host_us + known, est.rate, est.error_us, est.epoch + steps)

    def _estimate(self) -> ClockEstimate | None:
        """The device clock's estimate at the newest sample (the caller holds the lock)."""
        last = self._collector.last_us
        return None if last is None else self._collector.device_clock.estimate(last)

    def status(self) -> dict[str, int | float | str]:
        """State (connecting | streaming | disconnected | closed), cumulative counters,
        ``seconds_since_frame`` (-1 before the first frame; a silent device shows here), the device
        clock's estimated drift (``clock_drift_ppm``, + when it runs fast) and stated error
        (``clock_error_us``, -1 before the first frame) and its jumps (``clock_resets``)."""
        with self._lock:
            age = -1.0 if self._last_frame_s is None else time.monotonic() - self._last_frame_s
            est = self._estimate()
            return {
                "state": self._state,
                "port": self.port,
                **self._parser.stats.as_dict(),
                "wrong_taxels": self._collector.wrong_taxels,
                "bad_times": self._collector.bad_times,
                "overflowed": self._collector.overflowed,
                "samples_st": self._collector.samples[Channel.SINGLETACT],
                "samples_pvdf": self._collector.samples[Channel.PVDF],
                "bytes_received": self._bytes,
                "connects": self._connects,
                "reconnects": max(0, self._connects - 1),
                "last_error": self._last_error,
                "seconds_since_frame": round(age, 3),
                "clock_drift_ppm": 0.0 if est is None else round((1 / est.rate - 1) * 1e6, 1),
                "clock_error_us": -1 if est is None else est.error_us,
                "clock_resets": self._collector.device_clock.resets,
            }

    def close(self) -> None:
        self._closed.set()
        self._thread.join(timeout=2.0)
        with self._lock:
            self._state = "closed"

    def _set_state(self, state: str, error: BaseException | None = None) -> None:
        with self._lock:
            if not self._closed.is_set():
                self._state = state
            if error is not None:
                self._last_error = f"{type(error).__name__}: {error}"

    def _run(self) -> None:
        delay = self.backoff_s[0]
        while not self._closed.is_set():
            self._set_state("connecting")
            try:
                dev = self._open(self.port, baudrate=self.baudrate, timeout=READ_TIMEOUT_S, exclusive=True)
            except (serial.SerialException, OSError, ValueError) as exc:
                self._set_state("disconnected", exc)
                self._closed.wait(delay)
                delay = min(2 * delay, self.backoff_s[1])
                continue
            with self._lock:
                self._connects += 1
                self._parser.reset_buffer()  # a partial frame of the previous connection
            delay = self.backoff_s[0]
            try:
                self._stream(dev)
            except (serial.SerialException, OSError) as exc:
                self._set_state("disconnected", exc)
            finally:
                dev.close()
            self._closed.wait(delay)

    def _stream(self, dev: serial.SerialBase) -> None:
        with self._lock:
            if self._connects > 1:  # a reconnect: the mapping is announced anew
                self._collector.device_clock.mark_jump()
        while not self._closed.is_set():
            data = dev.read(dev.in_waiting or 1)
            if not data:
                continue
            now = time.monotonic()
            with self._lock:
                self._bytes += len(data)
                events = self._parser.feed(data)
                self._collector.add(events, now)
                if any(isinstance(ev, Frame) for ev in events):
                    self._last_frame_s = now
                    if not self._closed.is_set():
                        self._state = "streaming"
