"""A recorded session in memory: spikes, channels, decoded outputs, taxels, parameter revisions and
clock points, read from an MCAP recording (:func:`read_mcap`, of :mod:`.record`; needs ``mcap``) or a
``touchreal encode`` folder (:func:`read_encode_dir`); :class:`SpikeLog` gathers received spike frames.

Times are integer microseconds on the wire clock (the sensor clock plus a replay's segment offset).
``coverage_us[c] = (start, stop)``: the span in which every spike of class c was received (from
the stream's per-class finality ``final_us``), what a spike-train analysis takes as its window.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import protocol as P
from .clock import ClockMap, ClockPoint


@dataclass
class Coverage:
    """Per class, the span (us) in which every spike was received: from the first spike frame's
    ``final_us`` minus ``update_us`` (the span one frame finalises; earlier if a spike precedes it)
    to the last ``final_us``. ``update_us``: the stream's update interval (hello)."""

    update_us: int = 32000
    spans: dict[str, tuple[int, int]] = field(default_factory=dict)

    def push(self, frame: P.SpikesFrame) -> None:
        for k, c in enumerate(P.CLASSES):
            final = frame.final_us.get(c)
            if final is None:
                continue
            mine = frame.t_us[frame.cls == k]
            start = min(max(final - self.update_us, 0), int(mine.min()) if mine.size else final)
            lo, hi = self.spans.get(c, (start, final))
            self.spans[c] = (min(lo, start), max(hi, final))


@dataclass
class SpikeLog:
    """Spike frames in (sans-I/O), the concatenated spikes and their :class:`Coverage` out."""

    coverage: Coverage = field(default_factory=Coverage)
    _t: list[np.ndarray] = field(default_factory=list)
    _taxel: list[np.ndarray] = field(default_factory=list)
    _cls: list[np.ndarray] = field(default_factory=list)

    def push(self, frame: P.SpikesFrame) -> None:
        self._t.append(frame.t_us.astype(np.int64))
        self._taxel.append(frame.taxel)
        self._cls.append(frame.cls)
        self.coverage.push(frame)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t_us int64, taxel uint16, class index uint8), in arrival order."""
        if not self._t:
            return np.zeros(0, np.int64), np.zeros(0, np.uint16), np.zeros(0, np.uint8)
        return np.concatenate(self._t), np.concatenate(self._taxel), np.concatenate(self._cls)


@dataclass
class Channels:
    """``data[k, i, j]``: channel ``P.CHANNELS[j]`` of taxel ``taxels[i]`` at ``t_us[k]`` (NaN = missing)."""

    t_us: np.ndarray  # (n,) int64
    taxels: np.ndarray  # (m,) int
    data: np.ndarray  # (n, m, 4) float32


@dataclass
class Decoded:
    """``values[s, i, j]``: output ``outputs[j]`` of taxel ``taxels[i]`` at step ``t_us[s]``."""

    name: str
    outputs: list[str]
    t_us: np.ndarray
    taxels: np.ndarray
    values: np.ndarray  # (n_steps, m, n_outputs) float32


@dataclass(frozen=True)
class Trial:
    """A trial of an encode folder on the session's timeline (wire-clock us): it spans
    [``start_us``, ``stop_us``) and its own t = 0 is at ``origin_us``."""

    id: str
    start_us: int
    stop_us: int
    origin_us: int


@dataclass
class Session:
    """What a recording holds: spikes as ``t_us`` (int64, wire clock), ``taxel``, ``cls`` (index into
    ``CLASSES``), sorted by time; ``taxels``: ``[{"id", "x_mm", "y_mm"}]``; ``params``: one dict per
    parameter revision (``rev``, ``sha256``, ``params`` or None, ``source``); ``clock``: the clock points."""

    t_us: np.ndarray
    taxel: np.ndarray
    cls: np.ndarray
    taxels: list[dict[str, Any]]
    coverage_us: dict[str, tuple[int, int]]
    channels: Channels | None = None
    decoded: dict[str, Decoded] = field(default_factory=dict)
    params: list[dict[str, Any]] = field(default_factory=list)
    clock: list[ClockPoint] = field(default_factory=list)
    hello: dict[str, Any] | None = None
    source: str = ""
    trials: list[Trial] = field(default_factory=list)
    origin: int | None = None  #: the timeline's zero (us); None: the earliest recorded stamp
    sessions: list[str] = field(default_factory=list)  #: server sessions recorded (each restarts the wire clock)
    created_wall_us: int = 0  #: when the recording (or the encoding) was made, Unix epoch us

    @property
    def afferents(self) -> P.Afferents | None:
        """The population the spikes' ids address (the recorded hello's), None when they are taxels."""
        return P.hello_afferents(self.hello) if self.hello else None

    def origin_us(self) -> int:
        return self.origin if self.origin is not None else self.first_stamp_us()

    def first_stamp_us(self) -> int:
        """The earliest stamp of anything recorded (spikes, coverage, channel samples, decoded steps)."""
        cands = [int(self.t_us.min())] if self.t_us.size else []
        cands += [s for s, _ in self.coverage_us.values()]
        if self.channels is not None and self.channels.t_us.size:
            cands.append(int(self.channels.t_us.min()))
        cands += [int(d.t_us.min()) for d in self.decoded.values() if d.t_us.size]
        if not cands:
            raise ValueError(f"{self.source}: nothing was recorded")
        return min(cands)

    def wall_us_of(self, t_us: int) -> int | None:
        """Server wall time (us) of the stamp ``t_us`` by the clock model (None without clock points)."""
        if not self.clock:
            return None
        m = ClockMap(history=len(self.clock))
        for p in self.clock:
            m.update(p)
        return int(round(m.to_server_wall_us(t_us)))


def read_mcap(path: str | Path) -> Session:
    """A ``touchreal record`` MCAP file; ValueError if it is not one (CRCs are checked)."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    from .topics import CHANNELS_TOPIC, CLOCK_TOPIC, PREFIX, PROFILE

    path = Path(path)
    spikes: list[dict[str, Any]] = []
    ch_rows: list[dict[str, Any]] = []
    dec_rows: dict[str, list[dict[str, Any]]] = {}
    clock: list[ClockPoint] = []
    try:
        with path.open("rb") as fp:
            reader = make_reader(fp, validate_crcs=True)
            if reader.get_header().profile != PROFILE:
                raise ValueError(f"{path} is not a TouchReal recording (MCAP profile {reader.get_header().profile!r})")
            for _, channel, message in reader.iter_messages(log_time_order=False):
                body = json.loads(message.data)
                topic = channel.topic
                if topic.startswith(f"{PREFIX}/spikes/"):
                    spikes.append(body)
                elif topic == CHANNELS_TOPIC:
                    ch_rows.append(body)
                elif topic.startswith(f"{PREFIX}/decoded/"):
                    dec_rows.setdefault(topic.rsplit("/", 1)[1], []).append(body)
                elif topic == CLOCK_TOPIC:
                    clock.append(ClockPoint.from_json(body))
            attachments = [(a.name, json.loads(a.data)) for a in reader.iter_attachments()]
            meta = {m.name: m.metadata for m in reader.iter_metadata()}
    except (McapError, json.JSONDecodeError, KeyError) as exc:
        raise ValueError(f"{path}: not a readable TouchReal MCAP recording ({exc})") from exc
    hellos = [a for n, a in attachments if n == "hello.json"]
    params = sorted((a for n, a in attachments if n.startswith("params/")), key=lambda a: a["rev"])
    end = meta.get("touchreal.recording.end", {})
    started = int(json.loads(meta.get("touchreal.recording", {}).get("started_wall_us", "0")))
    coverage = {c: (int(s), int(e)) for c, (s, e) in json.loads(end.get("coverage_us", "{}")).items()}
    spikes.sort(key=lambda b: (b["t_us"], b["taxel"], P.CLASSES.index(b["class"])))
    hello = hellos[-1] if hellos else None
    return Session(
        t_us=np.array([b["t_us"] for b in spikes], np.int64),
        taxel=np.array([b["taxel"] for b in spikes], np.uint16),
        cls=np.array([P.CLASSES.index(b["class"]) for b in spikes], np.uint8),
        taxels=P.hello_taxels(hello) if hello else [],
        coverage_us=coverage, channels=_channels(ch_rows),
        decoded={name: _decoded(name, rows) for name, rows in dec_rows.items()},
        params=params, clock=sorted(clock, key=lambda p: (p.epoch, p.sensor_us)), hello=hello, source=str(path),
        created_wall_us=started, sessions=list(dict.fromkeys(str(h.get("session")) for h in hellos)))


def read_encode_dir(folder: str | Path, durations_s: dict[str, float] | None = None,
                    params: dict[str, Any] | None = None) -> Session:
    """A ``touchreal encode`` output folder (``<trial>.json`` = ``{"SA1": [t_s, ...], ...}``, one
    taxel) with its trials laid end to end on one timeline. ``durations_s``: trial id -> duration
    (the dataset manifest's ``duration_s``, in its order); without it a trial lasts up to the whole
    second after its last spike. A trial whose spikes start before its t = 0 (the reference clock)
    begins that much earlier. ``params``: the parameter set it was encoded with
    (``{"rev", "sha256", "params", "source"}``). ValueError for anything else in the folder."""
    folder = Path(folder)
    files = {f.stem: f for f in sorted(folder.glob("*.json"))}
    order = [t for t in durations_s if t in files] if durations_s else list(files)
    if not order:
        raise ValueError(f"{folder}: no <trial>.json files of touchreal encode")
    t_all, c_all, trials, cursor, classes = [], [], [], 0, set()
    for tid in order:
        trains = _trains(files[tid])
        times = np.concatenate([np.zeros(1)] + list(trains.values()))
        first, last = float(times.min()), float(times.max())
        origin = cursor - int(round(first * 1e6))
        dur = durations_s[tid] if durations_s else float(np.floor(last) + 1.0)
        stop = origin + max(int(round(dur * 1e6)), int(round(last * 1e6)) + 1)
        for c, t in trains.items():
            t_all.append(origin + np.round(t * 1e6).astype(np.int64))
            c_all.append(np.full(t.size, P.CLASSES.index(c), np.uint8))
            classes.add(c)
        trials.append(Trial(tid, cursor, stop, origin))
        cursor = stop
    t = np.concatenate(t_all)
    order_ix = np.argsort(t, kind="stable")
    return Session(t_us=t[order_ix], taxel=np.zeros(t.size, np.uint16), cls=np.concatenate(c_all)[order_ix],
                   taxels=[{"id": 0, "x_mm": 0.0, "y_mm": 0.0}], coverage_us={c: (0, cursor) for c in P.CLASSES if c in classes},
                   params=[params] if params else [], source=str(folder), trials=trials, origin=0,
                   created_wall_us=int(max(f.stat().st_mtime for f in files.values()) * 1e6))


def _trains(path: Path) -> dict[str, np.ndarray]:
    try:
        body = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not readable JSON ({exc})") from exc
    if not isinstance(body, dict) or not body or set(body) - set(P.CLASSES):
        raise ValueError(f"{path}: expected {{class: [spike times in s]}} with classes from {list(P.CLASSES)}")
    out = {}
    for c, v in body.items():
        if not isinstance(v, list) or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
            raise ValueError(f"{path}: {c} must be a list of spike times (s)")
        t = np.array(v, np.float64)
        if not np.isfinite(t).all():
            raise ValueError(f"{path}: {c} has non-finite spike times")
        out[c] = t
    return out


def _floats(rows: Iterable[Any]) -> np.ndarray:
    return np.array([[np.nan if v is None else v for v in r] for r in rows], np.float32)


def _channels(rows: list[dict[str, Any]]) -> Channels | None:
    if not rows:
        return None
    rows.sort(key=lambda b: b["t_us"])
    taxels = sorted({t for b in rows for t in b["taxels"]})
    col = {t: i for i, t in enumerate(taxels)}
    data = np.full((len(rows), len(taxels), len(P.CHANNELS)), np.nan, np.float32)
    for k, b in enumerate(rows):
        idx = [col[t] for t in b["taxels"]]
        for j, c in enumerate(P.CHANNELS):
            data[k, idx, j] = _floats([b[c]])[0]
    return Channels(np.array([b["t_us"] for b in rows], np.int64), np.array(taxels), data)


def _decoded(name: str, rows: list[dict[str, Any]]) -> Decoded:
    rows.sort(key=lambda b: b["t_us"])
    taxels = sorted({t for b in rows for t in b["taxels"]})
    col = {t: i for i, t in enumerate(taxels)}
    n_out = len(rows[0]["outputs"])
    values = np.full((len(rows), len(taxels), n_out), np.nan, np.float32)
    for s, b in enumerate(rows):
        values[s, [col[t] for t in b["taxels"]]] = _floats(b["values"])
    return Decoded(name, list(rows[0]["outputs"]), np.array([b["t_us"] for b in rows], np.int64), np.array(taxels), values)
