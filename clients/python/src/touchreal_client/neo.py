"""Received spikes -> neo SpikeTrains for neo/elephant analyses (extra ``[neo]``).

One :class:`neo.core.SpikeTrain` per (taxel, class), in seconds on the wire clock (stamp / 1e6),
with ``t_start``/``t_stop`` from the stream's per-class finality (:class:`~.session.Coverage`: every
spike of the class in that span was received), so rates computed on it are not biased by the
edges. Annotations: ``taxel``, ``afferent_class``, ``x_mm``, ``y_mm``.

>>> from touchreal_client.neo import spiketrains
>>> trains = spiketrains(read_mcap("session.mcap"))          # or spiketrains(frames, hello=s.hello)
>>> elephant.statistics.mean_firing_rate(trains[0])
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
import quantities as pq
from neo.core import SpikeTrain

from . import protocol as P
from .session import Coverage, Session, SpikeLog


def spiketrains(source: Session | Iterable[P.SpikesFrame], hello: dict[str, Any] | None = None) -> list[SpikeTrain]:
    """Spike trains of a recording (:class:`~.session.Session`) or of received spike frames (other
    frames are skipped). ``hello``: the stream's hello, for the taxel positions and the update
    interval (frames only; a recording carries its own). Taxels: the hello's (or the recording's),
    plus any that spiked; classes: those the frames were final for."""
    if isinstance(source, Session):
        t, taxel, cls = source.t_us, source.taxel, source.cls
        coverage, layout = source.coverage_us, source.taxels
    else:
        log = SpikeLog(Coverage(int((hello or {}).get("update_us", 32000))))
        for f in source:
            if isinstance(f, P.SpikesFrame):
                log.push(f)
        (t, taxel, cls), coverage, layout = log.arrays(), log.coverage.spans, P.hello_taxels(hello or {"taxels": []})
    pos = {int(x["id"]): (float(x.get("x_mm", 0.0)), float(x.get("y_mm", 0.0))) for x in layout}
    out = []
    for tx in sorted(set(pos) | set(np.unique(taxel).tolist())):
        for k, c in enumerate(P.CLASSES):
            if c not in coverage:
                continue
            lo, hi = coverage[c]
            times = np.sort(t[(taxel == tx) & (cls == k)]).astype(np.float64) / 1e6
            x, y = pos.get(tx, (np.nan, np.nan))
            out.append(SpikeTrain(times * pq.s, t_start=lo / 1e6 * pq.s, t_stop=hi / 1e6 * pq.s,
                                  name=f"taxel {tx} {c}", taxel=tx, afferent_class=c, x_mm=x, y_mm=y))
    return out
