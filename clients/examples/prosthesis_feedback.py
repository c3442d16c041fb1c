"""Prosthesis feedback: live afferent spikes -> electrical stimulation pulse trains, written to CSV.

Over a skin of taxels each (taxel, class) pair drives one stimulation channel. Over an afferent
population (``serve --population``), channels take groups of afferents, as the electrodes of a
biomimetic intraneural interface each recruit a fascicle whose afferents innervate one patch of
skin: ``--electrodes RxC`` lays R x C fields over the population, and each (field, class) is a
channel driven by its afferents' mean spike rate. Per class, the spike rate over a sliding
window modulates either the **pulse rate** (``rate``: fixed amplitude, rate between ``min_hz`` and
``max_hz``) or the **pulse amplitude** (``amplitude``: fixed rate, amplitude between ``min_ua`` and
``max_ua``); a channel whose spike rate is below ``threshold_hz`` is silent. Pulses are scheduled on
the sensor clock, one update at a time, as each class becomes final (``final_us``).

    python prosthesis_feedback.py --url http://127.0.0.1:8765 --seconds 10 --out pulses.csv \
        --map SA1=amplitude,RA=rate,PC=rate

CSV columns: ``t_us`` (sensor clock), ``channel`` (the taxel, or the field), ``class``,
``amplitude_uA``, ``width_us``. Needs
only ``touchreal-client``. The numbers are illustrative defaults, not a clinical protocol.
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from collections import deque
from dataclasses import dataclass

from collections.abc import Mapping

import numpy as np
from touchreal_client import CLASSES, Client, SpikesFrame, Subscription
from touchreal_client import protocol as P


@dataclass(frozen=True)
class ChannelMap:
    """How one class's spike rate (Hz) becomes pulses."""

    mode: str = "rate"  #: "rate" or "amplitude"
    window_us: int = 100_000  #: spike-rate window
    threshold_hz: float = 5.0  #: below it: no pulses
    full_hz: float = 200.0  #: spike rate mapped to the top of the range
    min_hz: float = 10.0  #: pulse rate range (rate mode)
    max_hz: float = 200.0
    fixed_hz: float = 50.0  #: pulse rate (amplitude mode)
    min_ua: float = 100.0  #: amplitude range (amplitude mode)
    max_ua: float = 1000.0
    fixed_ua: float = 500.0  #: amplitude (rate mode)
    width_us: int = 200  #: pulse width

    def pulse(self, spike_rate_hz: float) -> tuple[float, float] | None:
        """(pulse rate Hz, amplitude uA) for a spike rate, or None below the threshold."""
        if spike_rate_hz < self.threshold_hz:
            return None
        x = min(spike_rate_hz / self.full_hz, 1.0)
        if self.mode == "rate":
            return self.min_hz + x * (self.max_hz - self.min_hz), self.fixed_ua
        return self.fixed_hz, self.min_ua + x * (self.max_ua - self.min_ua)


def electrode_groups(afferents: P.Afferents, rows: int, cols: int) -> dict[int, int]:
    """Afferent id -> field (0 .. rows x cols - 1, row-major from the lowest x and y): R x C equal
    fields over the population's bounding box."""
    lo, hi = afferents.xy_mm.min(axis=0), afferents.xy_mm.max(axis=0)
    span = np.maximum(hi - lo, 1e-9)
    ix = np.minimum(((afferents.xy_mm[:, 0] - lo[0]) / span[0] * cols).astype(int), cols - 1)
    iy = np.minimum(((afferents.xy_mm[:, 1] - lo[1]) / span[1] * rows).astype(int), rows - 1)
    return dict(enumerate((iy * cols + ix).tolist()))


class StimulationMapper:
    """Sans-I/O: spike frames in, pulses ``(t_us, channel, class, amplitude_uA, width_us)`` out.

    ``groups`` (id -> channel, e.g. :func:`electrode_groups`): a channel's spike rate is the mean rate
    of its afferents of the class; None: each id (taxel) is its own channel."""

    def __init__(self, maps: dict[str, ChannelMap], groups: Mapping[int, int] | None = None,
                 classes_of: Mapping[int, str] | None = None):
        bad = set(maps) - set(CLASSES)
        if bad or any(m.mode not in ("rate", "amplitude") for m in maps.values()):
            raise ValueError(f"classes must be in {CLASSES} and modes 'rate' or 'amplitude', got {maps}")
        self.maps = maps
        self.groups = groups
        self._members: dict[tuple[int, str], int] = {}  #: per (channel, class): afferents it takes
        if groups is not None:
            if classes_of is None:
                raise ValueError("groups need each afferent's class (classes_of)")
            for a, g in groups.items():
                key = (g, classes_of[a])
                self._members[key] = self._members.get(key, 0) + 1
        self._spikes: dict[tuple[int, str], deque[int]] = {}
        self._next_pulse: dict[tuple[int, str], int] = {}
        self._done_us: dict[str, int] = {}  #: per class: pulses scheduled up to here

    def push(self, frame: SpikesFrame) -> list[tuple[int, int, str, float, int]]:
        for t, unit, k in zip(frame.t_us.tolist(), frame.taxel.tolist(), frame.cls.tolist()):
            if CLASSES[k] in self.maps:
                channel = unit if self.groups is None else self.groups[unit]
                self._spikes.setdefault((channel, CLASSES[k]), deque()).append(t)
        out: list[tuple[int, int, str, float, int]] = []
        for cls, m in self.maps.items():
            final = frame.final_us.get(cls)
            if final is None:
                continue
            start = self._done_us.get(cls, final)
            self._done_us[cls] = final
            for (taxel, c), times in self._spikes.items():
                if c == cls:
                    out += self._schedule(taxel, cls, m, times, start, final)
        out.sort()
        return out

    def _schedule(self, taxel: int, cls: str, m: ChannelMap, times: deque[int], start: int, end: int):
        while times and times[0] < end - m.window_us:
            times.popleft()
        rate = sum(1 for t in times if t < end) / (m.window_us / 1e6) / self._members.get((taxel, cls), 1)
        p = m.pulse(rate)
        key = (taxel, cls)
        if p is None:
            self._next_pulse.pop(key, None)
            return []
        hz, ua = p
        period = int(round(1e6 / hz))
        t = max(self._next_pulse.get(key, start), start)
        pulses = []
        while t < end:
            pulses.append((t, taxel, cls, round(ua, 1), m.width_us))
            t += period
        self._next_pulse[key] = t
        return pulses


def parse_map(text: str) -> dict[str, ChannelMap]:
    """``SA1=amplitude,RA=rate`` -> per-class maps with the default ranges."""
    maps = {}
    for item in filter(None, text.split(",")):
        cls, _, mode = item.partition("=")
        maps[cls.strip()] = ChannelMap(mode=mode.strip() or "rate")
    return maps


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--url", default="http://127.0.0.1:8765")
    ap.add_argument("--seconds", type=float, default=10.0, help="how long to run (s)")
    ap.add_argument("--out", default="pulses.csv")
    ap.add_argument("--taxels", default=None, help="comma list (default all)")
    ap.add_argument("--map", default="SA1=amplitude,RA=rate,PC=rate", help="per class: rate or amplitude")
    ap.add_argument("--electrodes", default="2x2", help="over a population: R x C fields, one channel per field and "
                    "class (default 2x2)")
    args = ap.parse_args(argv)
    try:
        maps = parse_map(args.map)
        StimulationMapper(maps)
        rows, _, cols = args.electrodes.partition("x")
        rows, cols = int(rows), int(cols)
        if not (1 <= rows <= 64 and 1 <= cols <= 64):
            raise ValueError("--electrodes: R x C with 1 <= R, C <= 64")
    except ValueError as exc:
        ap.error(str(exc))
    taxels = [int(t) for t in args.taxels.split(",")] if args.taxels else None
    sub = Subscription(taxels=taxels, classes=[c for c in CLASSES if c in maps])
    n = 0
    with Client(args.url) as tr, open(args.out, "w", newline="") as f:
        tr.wait_ready(60)
        out = csv.writer(f)
        out.writerow(["t_us", "channel", "class", "amplitude_uA", "width_us"])
        end = time.monotonic() + args.seconds
        with tr.stream(sub) as s:
            afferents = P.hello_afferents(s.hello)
            if afferents is None:
                mapper = StimulationMapper(maps)
            else:
                mapper = StimulationMapper(maps, electrode_groups(afferents, rows, cols),
                                           {a: CLASSES[k] for a, k in enumerate(afferents.cls.tolist())})
            for frame in s.spikes():
                pulses = mapper.push(frame)
                out.writerows(pulses)
                n += len(pulses)
                if time.monotonic() >= end:
                    break
            print(f"{n} pulses in {args.out}; stream: {s.stats.frames} frames, {s.stats.missed_frames} missed",
                  file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
