"""Live simulated sensor: a scripted scene streamed chunk by chunk (sans-I/O), plus a real-time pacer.

:class:`SceneSource` plays a :class:`Scene` (stimuli at given onsets and contact positions, looped
or not) through the robot dynamics and the e-skin physics of N taxels. ``advance(n)`` /
``read(duration_s)`` return the next raw samples as a :class:`~touchreal.raw.RawChunk`
(SingleTact at 100 Hz in N, PVDF at 2 kHz in V, times in s on one clock), continuing seamlessly
from the previous call; nothing sleeps. Same seed -> identical arrays, however the reads are split.

:class:`RealTimePacer` is the thin wall-clock layer for the service: it yields chunks of a source
as real time passes (its clock and sleep functions are injectable for tests).

:func:`default_scene` is the service's default script: presses at several depths, vibration
bursts and texture slides, looping forever.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Iterator, Sequence

import numpy as np

from .eskin import FS_HZ, ContactInput, ESkin, SkinParams
from .reads import TickReads
from ..raw import RawChunk
from .stimuli import RampHold, Robot, RobotParams, SineBurst, Stimulus, TextureSlide, executed_command

_LEAD_S = 0.05  # a tick belongs to the next event this long before its onset (robot latency margin)


@dataclass(frozen=True)
class SceneEvent:
    """One stimulus of a scene: commanded ``onset_s`` (s) and contact centre ``xy_mm`` (mm)."""

    onset_s: float
    stimulus: Stimulus
    xy_mm: tuple[float, float] = (0.0, 0.0)

    @property
    def end_s(self) -> float:
        return self.onset_s + self.stimulus.duration_s


@dataclass(frozen=True)
class Scene:
    """Stimuli in time order; ``loop_s`` (s) repeats the script with that period, None plays it once.

    Between events the probe is lifted (unless a resting :class:`SineBurst` keeps it on the skin)
    and hovers over the position of the last event.
    """

    events: tuple[SceneEvent, ...]
    loop_s: float | None = None

    def __post_init__(self) -> None:
        if not self.events:
            raise ValueError("a scene needs at least one event")
        on = [e.onset_s for e in self.events]
        if any(b <= a for a, b in zip(on, on[1:])):
            raise ValueError("scene events must have increasing onsets")
        for a, b in zip(self.events, self.events[1:]):
            if b.onset_s - _LEAD_S < a.end_s + 0.1:
                raise ValueError(f"events at {a.onset_s} s and {b.onset_s} s overlap (keep >= 0.15 s between them)")
        if self.loop_s is not None:
            if self.loop_s <= self.events[-1].end_s + 0.1 - (self.events[0].onset_s - _LEAD_S):
                raise ValueError("loop_s is shorter than the script")

    def command(self, t: np.ndarray, robot: RobotParams) -> dict[str, np.ndarray]:
        """Robot depth/x commands, exciter displacement, contact position and contactor at times ``t`` (s)."""
        t = np.asarray(t, float)
        n = t.size
        starts = np.array([e.onset_s - _LEAD_S for e in self.events])
        tl = t if self.loop_s is None else np.mod(t - starts[0], self.loop_s) + starts[0]
        idx = np.searchsorted(starts, tl, side="right") - 1
        if self.loop_s is None:
            idx = np.maximum(idx, 0)  # before the first event: its own (pre-onset) command
        out = {
            "depth": np.zeros(n), "x": np.zeros(n), "vib": np.zeros(n), "xy": np.zeros((n, 2)),
            "comb": np.zeros(n, bool), "spacing": np.zeros(n),
        }
        for i in np.unique(idx):
            ev = self.events[i]
            sel = idx == i
            trel = tl[sel] - ev.onset_s
            d, x = executed_command(ev.stimulus, trel, robot)
            out["depth"][sel] = d
            out["x"][sel] = x
            out["vib"][sel] = ev.stimulus.vibration(trel - robot.exciter_latency_s)
            out["xy"][sel] = ev.xy_mm
            out["comb"][sel] = ev.stimulus.contactor == "comb"
            out["spacing"][sel] = ev.stimulus.spacing_mm
        return out


def default_scene(positions_mm: Sequence[Sequence[float]] = ((0.0, 0.0),), skin: SkinParams | None = None) -> Scene:
    """The live script: press-hold-release at several depths and speeds, vibration bursts, texture slides.

    One pass of the script is played at each of ``positions_mm`` (contact centres, mm) in turn, so a
    taxel array sees stimuli on and off its taxels; the whole loop repeats forever.
    """
    skin = skin or SkinParams()
    script: list[Stimulus] = [
        RampHold(0.6, 20.0, 20.0, 0.8),
        RampHold(1.2, 40.0, 40.0, 0.6),
        RampHold(1.8, 65.0, 40.0, 1.0),
        RampHold(1.0, 95.0, 95.0, 0.0),
        SineBurst.calibrated(30.0, skin, resting=False),
        SineBurst.calibrated(100.0, skin, resting=False),
        SineBurst.calibrated(265.0, skin, resting=False),  # off the mains harmonics the PVDF notches (250 Hz: 50 Hz x 5)
        TextureSlide(0.5, slide_s=1.5),
        TextureSlide(2.0, slide_s=1.5),
        TextureSlide(4.0, slide_s=1.5),
    ]
    events, t = [], 0.3
    for xy in positions_mm:
        for stim in script:
            events.append(SceneEvent(round(t, 4), stim, (float(xy[0]), float(xy[1]))))
            t += stim.duration_s + 0.6
    return Scene(tuple(events), loop_s=round(t, 4))


class SceneSource(TickReads):
    """Sans-I/O streaming source: the next raw samples of N simulated taxels playing a scene.

    Args:
        scene: the script (default: :func:`default_scene` over the taxel positions' centre).
        taxels_xy_mm: (N, 2) taxel centres (mm).
        seed: reproducibility (same seed -> identical arrays, however reads are chunked).
        skin, robot: physical parameters.
        t0_s, st_phase_ticks: time of the first PVDF tick (s; random within the first tick period if None,
            any value to start the clock elsewhere, e.g. past 2^32 us) and SingleTact phase.
    """

    def __init__(
        self,
        scene: Scene | None = None,
        *,
        taxels_xy_mm: Sequence[Sequence[float]] | np.ndarray = ((0.0, 0.0),),
        seed: int | np.random.SeedSequence | None = None,
        skin: SkinParams | None = None,
        robot: RobotParams | None = None,
        t0_s: float | None = None,
        st_phase_ticks: int | None = None,
    ) -> None:
        self.skin_params = skin or SkinParams()
        self.robot_params = robot or RobotParams()
        self.scene = scene or default_scene(skin=self.skin_params)
        ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        clock_ss, skin_ss = ss.spawn(2)
        clock = np.random.default_rng(clock_ss)
        t0 = float(clock.uniform(0.0, 1.0 / FS_HZ)) if t0_s is None else float(t0_s)
        phase = int(clock.integers(0, 20)) if st_phase_ticks is None else int(st_phase_ticks)
        first = self.scene.command(np.array([t0]), self.robot_params)
        # states start relaxed at the first contact (e.g. an exciter probe resting on the skin)
        self.eskin = ESkin(
            taxels_xy_mm, self.skin_params, skin_ss, t0_s=t0, st_phase_ticks=phase,
            initial_depth_mm=float(first["depth"][0]), initial_xy_mm=tuple(first["xy"][0]),
        )
        self.robot = Robot(self.robot_params, float(first["depth"][0]), float(first["x"][0]))
        self._requested_s = t0 - math.fmod(t0, 1.0 / FS_HZ)  # the clock's start (0 unless t0_s is far out)

    @property
    def n_taxels(self) -> int:
        return self.eskin.n_taxels

    @property
    def tick(self) -> int:
        """Index of the next PVDF tick (2 kHz) since the clock's start."""
        return self.eskin.tick

    @property
    def clock_t0_s(self) -> float:
        return self.eskin.t0_s

    @property
    def st_phase(self) -> int:
        """The tick (0-19) of the first SingleTact sample: SingleTact samples fall on ticks = this mod 20."""
        return self.eskin.st_phase

    def _advance(self, n: int) -> RawChunk:
        k = self.eskin.tick + np.arange(n)
        t = self.eskin.t0_s + k / FS_HZ
        cmd = self.scene.command(t, self.robot_params)
        depth, x = self.robot.track(cmd["depth"], cmd["x"])
        contact = ContactInput(depth, cmd["vib"], cmd["xy"], cmd["comb"], x, cmd["spacing"])
        return self.eskin.process(contact)


@dataclass
class RealTimePacer:
    """Yields chunks of ``source`` in step with wall-clock time (one every ``chunk_s`` seconds).

    The k-th chunk holds the source samples of ``((k - 1) * chunk_s, k * chunk_s]`` and is released
    when the wall clock reaches ``start + k * chunk_s``. A consumer that falls behind gets the
    missed chunks back to back (nothing is dropped or duplicated). ``clock`` and ``sleep`` are
    injectable for tests.
    """

    source: SceneSource
    chunk_s: float = 0.032
    clock: Callable[[], float] = time.monotonic
    sleep: Callable[[float], None] = time.sleep
    _stop: bool = field(default=False, init=False)

    def stop(self) -> None:
        """End the iteration after the current chunk."""
        self._stop = True

    def __iter__(self) -> Iterator[RawChunk]:
        start = self.clock()
        k = 0
        while not self._stop:
            k += 1
            wait = start + k * self.chunk_s - self.clock()
            if wait > 0:
                self.sleep(wait)
            yield self.source.read(self.chunk_s)
