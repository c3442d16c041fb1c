"""Lab Streaming Layer outlets of a ``/v1/stream``: ``touchreal bridge lsl --from URL`` (extra ``lsl``: pylsl).

Two outlets (``source_id`` ``touchreal-<session>-spikes`` / ``-channels``, so a recorder reattaches
after a bridge restart on the same service session):

* ``<name>-spikes`` (type ``Spikes``, irregular rate, int32 x 2): one sample per spike,
  ``[taxel, class]`` with class 0 = SA1, 1 = RA, 2 = PC;
* ``<name>-channels`` (type ``Force``, regular ``5000 / decimation`` Hz, float32 x 4 per taxel):
  ``<taxel>.ST`` [N] (the preprocessed force), ``<taxel>.dST`` [N/s], ``<taxel>.PVDF`` [V],
  ``<taxel>.dPVDF`` [V/s] for every taxel of the hello, in taxel order (NaN where the stream has none).

Each sample's LSL timestamp is the wall time of its wire stamp by the stream's clock model (server
wall clock, then this machine's by the ``time`` offset, then LSL's ``local_clock()`` domain), not its
time of arrival: a spike at the acquisition time of the sample stamped like it, a channel sample at
its own. The StreamInfo XML (``desc``) carries the channel labels and units, the class names, the
taxel layout (id, x_mm, y_mm), the service session and parameter revision.

From a service running an afferent population (``addresses: "afferents"``) there is the spikes outlet
only, one sample per spike ``[afferent, class]``, and its ``desc`` lists the afferents (id, class, x_mm,
y_mm, model) beside the taxels (a population has no channels stream).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from typing import Any

import numpy as np

from .. import protocol as P
from ..stream import AsyncStream
from . import FIRST_SYNC_SAMPLES, forward

log = logging.getLogger("touchreal_client.bridges.lsl")


def lsl_minus_wall_s(tries: int = 3) -> float:
    """LSL's ``local_clock()`` minus this machine's wall clock (s), read between two wall reads; of
    ``tries`` reads the one with the tightest bracket (a thread preempted between the reads would
    otherwise put its pause into the offset)."""
    import pylsl

    best = (math.inf, 0.0)
    for _ in range(tries):
        a = time.time()
        lsl = pylsl.local_clock()
        b = time.time()
        best = min(best, (b - a, lsl - (a + b) / 2.0))
    return best[1]


def _describe(info: Any, hello: dict[str, Any], labels: list[str], units: list[str]) -> None:
    """Fill ``info.desc()``: channels (label, unit), classes, taxel layout, acquisition, clock."""
    desc = info.desc()
    chans = desc.append_child("channels")
    for label, unit in zip(labels, units):
        ch = chans.append_child("channel")
        ch.append_child_value("label", label)
        ch.append_child_value("unit", unit)
    classes = desc.append_child("classes")
    for i, c in enumerate(P.CLASSES):
        cls = classes.append_child("class")
        cls.append_child_value("index", str(i))
        cls.append_child_value("name", c)
    layout = desc.append_child("taxels")
    for t in hello.get("taxels") or []:
        tx = layout.append_child("taxel")
        for key in ("id", "x_mm", "y_mm"):
            tx.append_child_value(key, str(t.get(key)))
    afferents = P.hello_afferents(hello)
    if afferents is not None:
        pop = desc.append_child("afferents")
        for i, (k, (x, y), m) in enumerate(zip(afferents.cls.tolist(), afferents.xy_mm.tolist(), afferents.model.tolist())):
            a = pop.append_child("afferent")
            for key, value in (("id", i), ("class", P.CLASSES[k]), ("x_mm", x), ("y_mm", y), ("model", m)):
                a.append_child_value(key, str(value))
    acq = desc.append_child("acquisition")
    acq.append_child_value("manufacturer", "TouchReal")
    acq.append_child_value("server", str(hello.get("server", "")))
    acq.append_child_value("session", str(hello.get("session", "")))
    acq.append_child_value("params_rev", str(hello.get("params", {}).get("rev", "")))
    acq.append_child_value("clock", "timestamps: wall time of the wire stamp by the stream's clock model, "
                                    "in the local_clock() domain")


class LslBridge:
    """LSL outlets fed from the stream at ``url`` (every class's spikes and every taxel's channels
    at 5 kHz / ``decimation``). :attr:`ready` is set once both outlets exist."""

    def __init__(self, url: str, *, name: str = "TouchReal", decimation: int = 25):
        self.url, self.name, self.decimation = url, name, decimation
        self.ready = asyncio.Event()
        self.stream: AsyncStream | None = None
        self.outlet_names: list[str] = []
        self.source_ids: dict[str, str] = {}  #: "spikes" / "channels" -> the outlet's source_id
        self._column: dict[int, int] = {}  #: taxel id -> its column block in the channels outlet

    async def run(self) -> None:
        """Push until cancelled or until the stream ends for good (then raises StreamClosed)."""
        async with AsyncStream(self.url, P.Subscription(streams=["spikes"])) as stream:
            self.stream = stream
            if P.hello_afferents(stream.hello) is None:  # a population's afferents have spikes only
                await stream.subscribe(streams=["spikes", "channels"], decimation=self.decimation)
            await stream.sync_clock(FIRST_SYNC_SAMPLES)
            spikes, channels = self._outlets(stream.hello)

            def push(frame: P.Frame) -> None:
                if isinstance(frame, P.SpikesFrame):
                    self._push_spikes(spikes, frame)
                elif isinstance(frame, P.ChannelsFrame) and channels is not None:
                    self._push_channels(channels, frame)

            await forward(stream, push, self.ready)

    def _outlets(self, hello: dict[str, Any]) -> tuple[Any, Any]:
        """The spikes outlet, and the channels outlet (None for a population)."""
        import pylsl

        session = str(hello.get("session", "unknown"))
        taxels = [int(t["id"]) for t in hello.get("taxels") or []]
        self._column = {t: i for i, t in enumerate(taxels)}
        population = P.hello_afferents(hello) is not None
        self.source_ids = {k: f"touchreal-{session}-{k}" for k in (("spikes",) if population else ("spikes", "channels"))}
        s_info = pylsl.StreamInfo(f"{self.name}-spikes", "Spikes", 2, pylsl.IRREGULAR_RATE, pylsl.cf_int32,
                                  self.source_ids["spikes"])
        _describe(s_info, hello, ["afferent" if population else "taxel", "class"], ["id", "index into classes"])
        if population:
            self.outlet_names = [s_info.name()]
            return pylsl.StreamOutlet(s_info), None
        rate = 5000.0 / self.decimation
        c_info = pylsl.StreamInfo(f"{self.name}-channels", "Force", len(taxels) * len(P.CHANNELS), rate,
                                  pylsl.cf_float32, self.source_ids["channels"])
        labels = [f"{t}.{c}" for t in taxels for c in P.CHANNELS]
        _describe(c_info, hello, labels, list(P.CHANNEL_UNITS) * len(taxels))
        self.outlet_names = [s_info.name(), c_info.name()]
        return pylsl.StreamOutlet(s_info), pylsl.StreamOutlet(c_info)

    def _lsl_times(self, t_us: np.ndarray) -> list[float] | None:
        """LSL timestamps (s) of wire stamps; None before the stream's first clock point."""
        assert self.stream is not None
        try:
            local_us = np.atleast_1d(self.stream.to_local(np.asarray(t_us, np.float64)))
        except LookupError:
            return None
        return (local_us / 1e6 + lsl_minus_wall_s()).tolist()

    def _push_spikes(self, outlet: Any, f: P.SpikesFrame) -> None:
        if f.t_us.size == 0:
            return
        times = self._lsl_times(f.t_us)
        if times is None:
            log.warning("dropping %d spikes that came before the stream's first clock point", f.t_us.size)
            return
        outlet.push_chunk(np.stack([f.taxel, f.cls], axis=1).astype(np.int32), times)

    def _push_channels(self, outlet: Any, f: P.ChannelsFrame) -> None:
        n = f.data.shape[0]
        if n == 0:
            return
        times = self._lsl_times(f.t0_us + f.period_us * np.arange(n, dtype=np.uint64))
        if times is None:
            log.warning("dropping %d channel samples that came before the stream's first clock point", n)
            return
        block = np.full((n, len(self._column), len(P.CHANNELS)), np.nan, np.float32)
        for i, t in enumerate(f.taxels.tolist()):
            col = self._column.get(t)
            if col is not None:
                block[:, col, :] = f.data[:, i, :]
        outlet.push_chunk(block.reshape(n, -1), times)
