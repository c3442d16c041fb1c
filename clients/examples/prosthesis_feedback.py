"""Prosthesis feedback: live afferent spikes -> electrical stimulation pulse trains, written to CSV.

Each (taxel, class) pair drives one stimulation channel. Per class, the spike rate over a sliding
window modulates either the **pulse rate** (``rate``: fixed amplitude, rate between ``min_hz`` and
``max_hz``) or the **pulse amplitude** (``amplitude``: fixed rate, amplitude between ``min_ua`` and
``max_ua``); a channel whose spike rate is below ``threshold_hz`` is silent. Pulses are scheduled on
the sensor clock, one update at a time, as each class becomes final (``final_us``).

    python prosthesis_feedback.py --url http://127.0.0.1:8765 --seconds 10 --out pulses.csv \
        --map SA1=amplitude,RA=rate,PC=rate

CSV columns: ``t_us`` (sensor clock), ``taxel``, ``class``, ``amplitude_uA``, ``width_us``. Needs
only ``touchreal-client``. The numbers are illustrative defaults, not a clinical protocol.
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from collections import deque
from dataclasses import dataclass

from touchreal_client import CLASSES, Client, SpikesFrame, Subscription


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


class StimulationMapper:
    """Sans-I/O: spike frames in, pulses ``(t_us, taxel, class, amplitude_uA, width_us)`` out."""

    def __init__(self, maps: dict[str, ChannelMap]):
        bad = set(maps) - set(CLASSES)
        if bad or any(m.mode not in ("rate", "amplitude") for m in maps.values()):
            raise ValueError(f"classes must be in {CLASSES} and modes 'rate' or 'amplitude', got {maps}")
        self.maps = maps
        self._spikes: dict[tuple[int, str], deque[int]] = {}
        self._next_pulse: dict[tuple[int, str], int] = {}
        self._done_us: dict[str, int] = {}  #: per class: pulses scheduled up to here

    def push(self, frame: SpikesFrame) -> list[tuple[int, int, str, float, int]]:
        for t, taxel, k in zip(frame.t_us.tolist(), frame.taxel.tolist(), frame.cls.tolist()):
            if CLASSES[k] in self.maps:
                self._spikes.setdefault((taxel, CLASSES[k]), deque()).append(t)
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
        rate = sum(1 for t in times if t < end) / (m.window_us / 1e6)
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
    args = ap.parse_args(argv)
    try:
        mapper = StimulationMapper(parse_map(args.map))
    except ValueError as exc:
        ap.error(str(exc))
    taxels = [int(t) for t in args.taxels.split(",")] if args.taxels else None
    sub = Subscription(taxels=taxels, classes=[c for c in CLASSES if c in mapper.maps])
    n = 0
    with Client(args.url) as tr, open(args.out, "w", newline="") as f:
        tr.wait_ready(60)
        out = csv.writer(f)
        out.writerow(["t_us", "taxel", "class", "amplitude_uA", "width_us"])
        end = time.monotonic() + args.seconds
        with tr.stream(sub) as s:
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
