"""Live sources for the service: the blocking layer over the sans-I/O sources.

Every live source hands the acquisition thread one :class:`~touchreal.raw.RawChunk` per
hop (``touchreal serve --hop-ms``, 5 ms by default) through ``next_chunk()`` (blocking about one
hop; ``None`` once the source has ended or was closed), and reports its state and counters through
``status()``. The simulated e-skin ends a hop with each SingleTact sample and halfway between, so
a SingleTact sample waits for no hop (the fast classes wait for the SingleTact).

A source's stream is a sequence of *segments*: the simulated e-skin and the serial reader have
one; a replay has one per trial, each on its own recording clock. ``segment`` counts them and
``offset_us`` is the integer offset that puts the current segment on the stream's monotonic sensor
clock (the encoder sees the trial's own clock, so a replayed trial's spikes equal ``touchreal
encode``'s; only the wire adds the offset).
"""

from __future__ import annotations

import logging
import math
import multiprocessing as mp
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from multiprocessing.context import BaseContext
from multiprocessing.shared_memory import SharedMemory
from typing import Protocol

import numpy as np

from touchreal_client.clock import ClockPoint

from ..recording import Dataset, Trial
from ..settings import PVDF_FS_HZ, ST_FS_HZ
from ..raw import RawChunk, taxel_grid
from .replay import ReplaySource
from ..simulator.large import LargeSkinSource
from ..simulator.scene import SceneSource, default_scene


log = logging.getLogger("touchreal.sources")

MAX_CATCH_UP_HOPS = 64  #: a sim or replay that fell behind hands over up to this many hops at once
SEGMENT_GRID_US = 160_000  #: segment offsets are multiples of this (lcm of 10 ms bins and 32 ms steps)
#: a replayed trial's span on the wire runs this long past its last sample, so that no spike of it (stamped at
#: most its sample's time + the class delay, <= 500 ms, + one 5 kHz grid sample) reaches the next trial's span;
#: it also covers the longest look-ahead (a 512 ms window: 512.5 ms). tests/test_replay_boundaries.py checks it
SEGMENT_GUARD_US = 1_100_000
#: shared memory for the simulated hops in flight between the simulation's process and the service (bytes; Docker
#: gives a container 64 MiB of /dev/shm by default): a skin whose hops need more gets fewer of them in flight
SIM_RING_BYTES = 32 << 20


class LiveSource(Protocol):
    """What the service's acquisition thread reads."""

    n_taxels: int
    positions_mm: np.ndarray  #: (n_taxels, 2) taxel centres, mm
    segment: int  #: index of the current segment (a replayed trial); the encoder restarts when it changes
    offset_us: int  #: sensor-clock offset of the current segment on the wire (us)

    def next_chunk(self) -> RawChunk | None: ...

    def clock(self) -> ClockPoint | None:
        """The clock model after the latest chunk: the wire-clock stamp of its end and the server
        wall time (us) at which that instant was acquired, the rate (wall us per sensor us) and the
        epoch (incremented whenever the mapping jumps); None before the first chunk."""
        ...

    def status(self) -> dict[str, int | float | str]: ...

    def close(self) -> None: ...


class _Paced:
    """Wall-clock pacing: the k-th chunk is released at ``start + k * period_s`` (:meth:`wait_next`),
    or at a time the source names (:meth:`wait_until`); missed ones come back to back, nothing is
    dropped. ``clock``/``sleep`` are injectable; ``close()`` wakes it."""

    def __init__(self, period_s: float, clock: Callable[[], float] = time.monotonic):
        self.period_s = period_s
        self.clock = clock
        self._closed = threading.Event()
        self._start: float | None = None
        self._start_wall_us = 0
        self._k = 0
        self._due_s = 0.0  #: the latest release, s after the start
        self.epoch = -1  #: increments at every (re)start of the schedule

    def wait_next(self) -> bool:
        """Sleep until the next release; False once closed."""
        self._k += 1
        return self.wait_until(self._k * self.period_s)

    def wait_until(self, t_s: float) -> bool:
        """Sleep until ``t_s`` (s) after the schedule's start (the first call); False once closed."""
        if self._start is None:
            self._start = self.clock()
            self._start_wall_us = time.time_ns() // 1000
            self.epoch += 1
        self._due_s = t_s
        wait = self._start + t_s - self.clock()
        if wait > 0:
            self._closed.wait(wait)
        return not self._closed.is_set()

    def passed(self, t_s: float) -> bool:
        """Whether ``t_s`` (s after the start) is already past; if so it becomes the latest release
        (a source that fell behind hands over that much more at once)."""
        if self._start is None or self._start + t_s > self.clock():
            return False
        self._due_s = t_s
        return True

    def late_s(self, t_s: float) -> float:
        """How long ago (s) ``t_s`` (s after the start) was due; negative before it, 0 before the start."""
        return 0.0 if self._start is None else self.clock() - (self._start + t_s)

    def take_passed(self, limit: int) -> int:
        """How many of the next regular releases (:meth:`wait_next`'s) are already past, up to
        ``limit``; they count as released (a source that fell behind hands them over at once)."""
        n = 0
        while n < limit and self.passed((self._k + 1) * self.period_s):
            self._k += 1
            n += 1
        return n

    def close(self) -> None:
        self._closed.set()

    def restart(self) -> None:
        """Start a new schedule at the next call (after a pause: no catching up)."""
        self._start, self._k = None, 0

    def release_wall_us(self) -> int:
        """Scheduled wall time (us) of the latest release: when its chunk's last instant was acquired."""
        return self._start_wall_us + int(round(self._due_s * 1e6))


def hop_ticks(update_s: float) -> int:
    """PVDF ticks (2 kHz) in a hop of ``update_s`` (s): the most a simulated hop holds."""
    return max(1, int(round(update_s * PVDF_FS_HZ)))


class SimHops:
    """The simulated e-skin cut into hops, unpaced (sans-I/O): :func:`~touchreal.simulator.scene.default_scene`
    over ``n_taxels`` taxels (a grid of 10 mm pitch), looping forever. With several taxels the script
    is played at the array's centre and over its first and last taxel in turn, so neighbouring taxels
    feel each touch differently (the skin's spatial response).

    ``touched`` (0-1) plays the large-skin scene instead (:mod:`~touchreal.simulator.large`): sparse
    contacts moving over the grid, that fraction of the taxels under one at a typical moment, the
    others reading the build's noise, hum and drift; its cost follows the touched taxels.

    Hops span ``update_s`` (rounded to PVDF ticks), on a grid phased so that a hop's newest sample is
    a SingleTact sample (with its PVDF tick) when the hop divides the SingleTact period (10 ms)."""

    load = 0.0  #: simulated in the caller's thread when read: its cost is the caller's (see SimHopsProcess.load)

    def __init__(self, n_taxels: int = 1, update_s: float = 0.032, seed: int = 0, t0_s: float | None = None,
                 touched: float | None = None):
        positions = taxel_grid(n_taxels)
        self.scene: SceneSource | LargeSkinSource
        if touched is None:
            spots = [(0.0, 0.0)] + ([tuple(positions[0]), tuple(positions[-1])] if n_taxels > 1 else [])
            self.scene = SceneSource(default_scene(spots), taxels_xy_mm=positions, seed=seed, t0_s=t0_s)
        else:
            self.scene = LargeSkinSource(positions, touched, seed=seed, t0_s=t0_s)
        self._hop_ticks = hop_ticks(update_s)
        self.zero_s = self.scene.requested_s  #: the sensor clock's instant (s) at which the stream starts

    def _hop_ticks_left(self) -> int:
        """PVDF ticks in the next hop: up to and with the next tick on the SingleTact phase (mod the hop)."""
        return (self.scene.st_phase - self.scene.tick) % self._hop_ticks + 1

    def next_newest_s(self) -> float:
        """The instant of the next hop's newest sample (s, sensor clock): the hop is over then."""
        return self.scene.time_s + (self._hop_ticks_left() - 1) / PVDF_FS_HZ

    def read_hop(self) -> RawChunk:
        """The next hop's samples."""
        return self.scene.advance(self._hop_ticks_left())

    def prefetch(self) -> None:
        """Nothing to do: a hop is simulated when it is read."""


class HopRing:
    """Slots in shared memory for the hops in flight from the simulation's process to the service, so
    that a hop's samples cross between the processes as one copy in and one copy out (through a pipe,
    pickled, the copies and the pipe's 64 KiB writes cost a third of the simulation's own CPU at
    16,384 taxels). A slot holds one hop of ``n_taxels`` taxels and at most ``pv_rows`` PVDF ticks (the
    SingleTact samples among them: at most ``pv_rows`` / 20 + 1): times float64 (s), samples float32 (as
    the simulated skin makes them). The owner (``name`` None) creates the memory; the other side attaches
    by its ``name``."""

    def __init__(self, n_taxels: int, pv_rows: int, slots: int, name: str | None = None):
        self.n_taxels, self.pv_rows, self.slots = n_taxels, pv_rows, slots
        self.st_rows, self.slot_bytes = self._layout(n_taxels, pv_rows)
        self.shm = SharedMemory(name=name, create=name is None, size=slots * self.slot_bytes if name is None else 0)

    @staticmethod
    def _layout(n_taxels: int, pv_rows: int) -> tuple[int, int]:
        """(SingleTact rows, bytes) of a slot."""
        st_rows = int(pv_rows * ST_FS_HZ // PVDF_FS_HZ) + 1
        rows = st_rows + pv_rows
        return st_rows, rows * (8 + 4 * n_taxels)

    @classmethod
    def slots_for(cls, n_taxels: int, pv_rows: int, wanted: int) -> int:
        """Slots within :data:`SIM_RING_BYTES` (at least 4, at most ``wanted``)."""
        return max(4, min(wanted, SIM_RING_BYTES // cls._layout(n_taxels, pv_rows)[1]))

    def _views(self, slot: int, n_st: int, n_pv: int) -> tuple[np.ndarray, ...]:
        """(st_t, st, pvdf_t, pvdf) of ``slot`` holding ``n_st`` SingleTact and ``n_pv`` PVDF rows."""
        off = slot * self.slot_bytes
        views = []
        for dtype, cap, rows, width in ((np.float64, self.st_rows, n_st, 0), (np.float32, self.st_rows, n_st, self.n_taxels),
                                        (np.float64, self.pv_rows, n_pv, 0), (np.float32, self.pv_rows, n_pv, self.n_taxels)):
            shape = (rows, width) if width else (rows,)
            views.append(np.ndarray(shape, dtype, self.shm.buf, off))
            off += np.dtype(dtype).itemsize * cap * max(width, 1)
        return tuple(views)

    def put(self, slot: int, hop: RawChunk) -> tuple[int, int]:
        """Copy ``hop`` into ``slot``; its (SingleTact, PVDF) row counts. A hop of other dtypes, or
        larger than a slot, is refused (ValueError) rather than stored changed."""
        n_st, n_pv = hop.st_t.size, hop.pvdf_t.size
        if not 0 <= slot < self.slots:
            raise ValueError(f"slot {slot} is not one of the ring's {self.slots}")
        dtypes = tuple(a.dtype for a in (hop.st_t, hop.st, hop.pvdf_t, hop.pvdf))
        if dtypes != (np.float64, np.float32, np.float64, np.float32):
            raise ValueError(f"a hop of dtypes {[str(d) for d in dtypes]} is not the ring's (times float64, samples float32): "
                             "storing it would change its values")
        if n_st > self.st_rows or n_pv > self.pv_rows or hop.st.shape[1:] != (self.n_taxels,) or hop.pvdf.shape[1:] != (self.n_taxels,):
            raise ValueError(f"a hop of {n_st} + {n_pv} rows x {hop.pvdf.shape[1:]} taxels does not fit a slot of "
                             f"{self.st_rows} + {self.pv_rows} rows x {self.n_taxels}")
        for view, a in zip(self._views(slot, n_st, n_pv), (hop.st_t, hop.st, hop.pvdf_t, hop.pvdf)):
            view[...] = a
        return n_st, n_pv

    def take(self, slot: int, n_st: int, n_pv: int) -> RawChunk:
        """A copy of the hop in ``slot`` (the slot can be written again)."""
        return RawChunk(*(v.copy() for v in self._views(slot, n_st, n_pv)))

    def close(self, unlink: bool = False) -> None:
        self.shm.close()
        if unlink:
            self.shm.unlink()


def _simulate_hops(conn: Connection, ring_name: str, slots: int, n_taxels: int, update_s: float, seed: int,
                   t0_s: float | None, touched: float | None = None) -> None:
    """The body of :class:`SimHopsProcess`'s process: sends the stream's zero (s) once its first hop is
    simulated, then per hop (newest sample's instant (s), slot, SingleTact rows, PVDF rows, wall time (s)
    its simulation took), the hop itself in that slot of the :class:`HopRing` ``ring_name``; never more than
    ``slots`` beyond those the parent has taken (it sends how many it took, an int), so a slot is written
    again only after the parent has taken its hop. Ends when the parent's end of ``conn`` closes."""
    hops = SimHops(n_taxels, update_s, seed, t0_s, touched)
    ring = HopRing(n_taxels, hop_ticks(update_s), slots, name=ring_name)
    sent = 0

    def simulated() -> tuple[float, int, int, int, float]:
        nonlocal sent
        t = time.perf_counter()
        newest, hop = hops.next_newest_s(), hops.read_hop()
        slot = sent % slots
        rows = ring.put(slot, hop)
        sent += 1
        return newest, slot, *rows, time.perf_counter() - t

    try:
        first = simulated()  # before the source counts as open
        conn.send(hops.zero_s)
        conn.send(first)
        credit = slots - 1
        while True:
            for _ in range(credit):
                conn.send(simulated())
            credit = int(conn.recv())
    except (EOFError, OSError, KeyboardInterrupt):
        return
    finally:
        ring.close()


def _processes() -> BaseContext:
    """Fork server with the skin's code loaded and its kernels warm (:mod:`.sim_warm`): a simulation process
    starts in milliseconds after the first (which pays the imports, about 1 s); forking the service itself
    (threads, sockets) would be unsafe."""
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload([f"{__package__}.sim_warm"])
    return ctx


class SimHopsProcess:
    """:class:`SimHops` run in a process of its own, up to ``ahead`` hops before they are taken, so that
    simulating the skin never competes with the service for its interpreter (the GIL). The hops' samples
    cross in shared memory (:class:`HopRing`, at most :data:`SIM_RING_BYTES`: a large skin gets fewer
    hops ahead), their descriptions and the credit of taken hops through a pipe; the caller still releases
    each at the instant of its newest sample. ``close()`` ends the process and frees the memory."""

    def __init__(self, n_taxels: int, update_s: float, seed: int = 0, t0_s: float | None = None, ahead: int = 32,
                 touched: float | None = None):
        ctx = _processes()
        ticks = hop_ticks(update_s)
        self._ring = HopRing(n_taxels, ticks, HopRing.slots_for(n_taxels, ticks, ahead))
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_simulate_hops, args=(child, self._ring.shm.name, self._ring.slots, n_taxels,
                                                              update_s, seed, t0_s, touched),
                                 name="touchreal-sim", daemon=True)
        self._proc.start()
        child.close()
        self._hops: deque[tuple[float, RawChunk, float]] = deque()
        self._taken = 0  #: hops taken since the last credit sent
        self._read = 0  #: hops read
        #: the simulation's recent real-time factor: wall time simulating per second of signal (about the
        #: last 20 hops; > 1: it cannot keep up in real time on this machine, under its present load)
        self.load = 0.0
        try:
            self.zero_s = float(self._receive())
        except BaseException:
            self.close()
            raise

    def _receive(self):
        try:
            return self._conn.recv()
        except (EOFError, OSError):
            raise self._ended() from None

    def _receive_hop(self) -> tuple[float, RawChunk, float]:
        newest, slot, n_st, n_pv, took_s = self._receive()
        return newest, self._ring.take(slot, n_st, n_pv), took_s

    def _ended(self) -> RuntimeError:
        self._proc.join(1.0)
        return RuntimeError(f"the simulated e-skin's process ended (exit code {self._proc.exitcode})")

    def prefetch(self) -> None:
        """Hand back the credit of the hops taken and have the next two in hand (waiting if the process is
        behind): called before a hop's release, so that neither the pipe nor the copy delays it after."""
        if self._taken:
            try:
                self._conn.send(self._taken)
            except OSError:
                raise self._ended() from None
            self._taken = 0
        while len(self._hops) < 2 or self._conn.poll():
            self._hops.append(self._receive_hop())

    def next_newest_s(self) -> float:
        if not self._hops:
            self.prefetch()
        return self._hops[0][0]

    def read_hop(self) -> RawChunk:
        if not self._hops:
            self.prefetch()
        self._taken += 1
        _, hop, took_s = self._hops.popleft()
        if hop.pvdf_t.size and self._read:  # not the first: it pays the skin's start (~14 ms) for as little as one tick
            self.load += 0.05 * (took_s * PVDF_FS_HZ / hop.pvdf_t.size - self.load)
        self._read += 1
        return hop

    def close(self) -> None:
        self._proc.terminate()
        self._proc.join(5.0)
        self._ring.close(unlink=True)


class SimLiveSource:
    """The simulated e-skin (:class:`SimHops`) in real time: a hop is released when the pace's clock
    reaches the instant of its newest sample (the sensor clock runs from its zero at the pace's
    start), and its clock point says so. A consumer that fell behind gets every hop already due in
    one chunk (up to :data:`MAX_CATCH_UP_HOPS`): fewer, larger calls until it has caught up.

    A simulation in a process of its own that cannot keep up (a skin too large for the machine)
    would hand over ever older hops, which a real-time consumer could only drop. When it is slower
    than real time (:attr:`SimHopsProcess.load` > 1) and its next hop is already later than one
    catch-up chunk (:data:`MAX_CATCH_UP_HOPS` hops), the schedule restarts at that hop instead (a
    new clock epoch, as after a pause; the samples stay continuous): the simulated skin runs slower
    than real time, and says so: ``status()`` gives ``sim_load``, ``fell_behind`` (the restarts),
    ``behind_s`` (how late their hops were) and ``behind_wall_us`` (the latest), and the log warns.
    A consumer that is late itself, behind a simulation that keeps up, sees its own lag.

    ``own_process``: simulate in a process of its own (:class:`SimHopsProcess`; the service does),
    so the acquisition thread only receives hops; otherwise in this thread (``scene`` is then the
    :class:`~touchreal.simulator.scene.SceneSource`). ``touched`` (0-1): the large-skin scene with that
    touched fraction (:class:`SimHops`); None: the default scene."""

    segment = 0

    def __init__(self, n_taxels: int = 1, update_s: float = 0.032, seed: int = 0, t0_s: float | None = None,
                 own_process: bool = False, touched: float | None = None):
        self.positions_mm = taxel_grid(n_taxels)
        self.n_taxels = n_taxels
        self.update_s = update_s
        self.touched = touched
        self.hops: SimHops | SimHopsProcess = (SimHopsProcess(n_taxels, update_s, seed, t0_s, touched=touched) if own_process
                                               else SimHops(n_taxels, update_s, seed, t0_s, touched))
        self.offset_us = 0
        self._pace = _Paced(update_s)
        self._zero_s = self.hops.zero_s
        self._chunks = 0
        self._clock: ClockPoint | None = None
        self.fell_behind = 0  #: schedule restarts because the simulation fell behind real time
        self.behind_s = 0.0  #: how late the hops were at those restarts, summed (s)
        self.behind_wall_us: int | None = None  #: wall clock (us) of the latest

    @property
    def scene(self) -> SceneSource | LargeSkinSource:
        """The scene being played (only when simulated in this thread)."""
        return self.hops.scene

    def next_newest_s(self) -> float:
        """The instant of the next hop's newest sample (s, sensor clock): the hop is over then."""
        return self.hops.next_newest_s()

    def read_hop(self) -> RawChunk:
        """The next hop's samples at once (no pacing: benchmarks and tests)."""
        return self.hops.read_hop()

    def next_chunk(self) -> RawChunk | None:
        try:
            return self._next_chunk()
        except RuntimeError:
            if self._pace._closed.is_set():  # closed meanwhile: the simulation's process was ended on purpose
                return None
            raise

    def _next_chunk(self) -> RawChunk | None:
        self.hops.prefetch()
        newest_s = self.next_newest_s()
        late = self._pace.late_s(newest_s - self._zero_s)
        if self.hops.load > 1.0 and late > MAX_CATCH_UP_HOPS * self.update_s:  # the simulation cannot keep up
            self._pace.restart()
            self._zero_s = newest_s - self.update_s
            self.fell_behind += 1
            self.behind_s += late
            self.behind_wall_us = time.time_ns() // 1000
            log.warning("the simulated skin (%d taxels) fell %.2f s behind real time: this machine cannot simulate it "
                        "in real time; its clock restarts (epoch %d)", self.n_taxels, late, self._pace.epoch + 1)
        if not self._pace.wait_until(newest_s - self._zero_s):
            return None
        self._chunks += 1
        hops = [self.read_hop()]
        while len(hops) < MAX_CATCH_UP_HOPS and self._pace.passed(self.next_newest_s() - self._zero_s):
            newest_s = self.next_newest_s()  # behind: the hops already acquired go in this chunk too
            hops.append(self.read_hop())
        chunk = hops[0] if len(hops) == 1 else RawChunk.concat(hops)
        # the skin is sampled in real time: the chunk's newest sample is "now" on the pace's schedule
        self._clock = ClockPoint(int(round(newest_s * 1e6)), self._pace.release_wall_us(), 1.0, 0, self._pace.epoch)
        return chunk

    def clock(self) -> ClockPoint | None:
        return self._clock

    def status(self) -> dict[str, int | float | str]:
        return {"state": "closed" if self._pace._closed.is_set() else "streaming", "kind": "sim", "chunks": self._chunks,
                "scene": "script" if self.touched is None else "large",
                **({} if self.touched is None else {"touched": self.touched}),
                "sim_load": round(self.hops.load, 3), "fell_behind": self.fell_behind, "behind_s": round(self.behind_s, 3),
                "behind_wall_us": self.behind_wall_us}

    def close(self) -> None:
        self._pace.close()
        if isinstance(self.hops, SimHopsProcess):
            self.hops.close()


class ReplayLiveSource:
    """Recorded trials played back to back, each a segment on its own clock, in real time x ``speed``.

    Segment i's samples go on the wire at ``offset_us`` = the sum of the previous segments' spans, a
    span being the trial's duration + :data:`SEGMENT_GUARD_US` rounded up to :data:`SEGMENT_GRID_US`:
    the stream's clock keeps increasing, every spike of a trial is stamped inside its own span, and
    every grid the stream is cut on (10 ms decoder bins, 32 ms steps) falls on the same instants of a
    trial (docs/stream-protocol.md). ``loop`` replays the list forever; otherwise the source ends
    after the last trial, and ``status()`` then gives ``end_us``, where the next span would begin.
    A replay waits for demand (``waits_for_demand``): it starts, and resumes, only while somebody
    subscribes, so nobody misses the beginning of a trial.
    """

    waits_for_demand = True
    replayed = True  #: not acquired in real time: the service never sheds it (server/runtime.py)

    def __init__(self, dataset: Dataset, trial_ids: Sequence[str] | None = None, update_s: float = 0.032,
                 speed: float = 1.0, loop: bool = False):
        entries = dataset.entries()
        if trial_ids:
            by_id = {e["id"]: e for e in entries}
            missing = [t for t in trial_ids if t not in by_id]
            if missing:
                raise ValueError(f"dataset {dataset.root} has no trial {missing}")
            entries = [by_id[t] for t in trial_ids]
        if not entries:
            raise ValueError(f"dataset {dataset.root} has no trials")
        if not speed > 0:
            raise ValueError("speed must be > 0")
        self.dataset, self.entries, self.loop = dataset, entries, loop
        self.update_s = update_s
        self.n_taxels = 1
        self.positions_mm = np.zeros((1, 2))
        self.segment = -1
        self.offset_us = 0
        self.trial_id = ""
        self._next_offset_us = 0
        self._player: ReplaySource | None = None
        self.speed = speed
        self._pace = _Paced(update_s / speed)
        self._ended = False
        self._clock: ClockPoint | None = None
        self._epoch = -1
        self._pace_epoch = -1

    def _open_next(self) -> bool:
        i = self.segment + 1
        if i >= len(self.entries) and not self.loop:
            return False
        entry = self.entries[i % len(self.entries)]
        trial: Trial = self.dataset.load(entry)
        self.segment, self.trial_id = i, entry["id"]
        self.offset_us = self._next_offset_us
        span = trial.duration_s * 1e6 + SEGMENT_GUARD_US
        self._next_offset_us += int(math.ceil(span / SEGMENT_GRID_US)) * SEGMENT_GRID_US
        self._player = ReplaySource(trial)
        return True

    def next_chunk(self) -> RawChunk | None:
        if self._ended or not self._pace.wait_next():
            return None
        if self._player is None or self._player.done:
            if not self._open_next():
                self._ended = True
                return None
            self._epoch += 1  # a new trial: the wire clock jumps to its offset
        elif self._pace.epoch != self._pace_epoch:
            self._epoch += 1  # resumed after a pause for demand
        self._pace_epoch = self._pace.epoch
        # behind (a fast replay on a slow machine): the hops already due within this trial go in this chunk too
        left = math.ceil((self._player.trial.duration_s - self._player.now_s) / self.update_s) - 1
        hops = 1 + self._pace.take_passed(min(MAX_CATCH_UP_HOPS - 1, left))
        start_s = self._player.now_s
        chunk = self._player.read(hops * self.update_s)
        # anchored at the chunk's first instant (acquired hops periods before its release): a new trial's first
        # point then precedes all its spikes, which a client maps by the latest point at or before them
        self._clock = ClockPoint(self.offset_us + int(round(start_s * 1e6)),
                                 self._pace.release_wall_us() - int(round(hops * self._pace.period_s * 1e6)),
                                 1.0 / self.speed, 0, self._epoch)
        return chunk

    def clock(self) -> ClockPoint | None:
        return self._clock

    def resume(self) -> None:
        """Continue after a pause for demand, in real time from now."""
        self._pace.restart()

    def status(self) -> dict[str, int | float | str]:
        state = "ended" if self._ended else ("closed" if self._pace._closed.is_set() else "streaming")
        out: dict[str, int | float | str] = {"state": state, "kind": "replay", "trial": self.trial_id, "segment": self.segment}
        if self._ended:
            out["end_us"] = self._next_offset_us
        return out

    def close(self) -> None:
        self._pace.close()
