"""What the connected subscribers need, as data: the pipeline computes exactly this.

A :class:`Demand` is immutable; the hub replaces it whenever a subscription changes and the
acquisition thread reads the current one once per update.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from touchreal_client.protocol import Subscription

from ..settings import CLASSES


@dataclass(frozen=True)
class Demand:
    """``columns[c]``: taxels whose class-c spikes are computed (for spikes subscribers or for
    decoders); ``channel_taxels``: taxels whose channels are wanted; ``decoders[name]``: taxels a
    decoder runs for; ``spikes[c]``: the part of ``columns`` wanted as spikes frames."""

    columns: Mapping[str, tuple[int, ...]] = field(default_factory=dict)
    channel_taxels: tuple[int, ...] = ()
    decoders: Mapping[str, tuple[int, ...]] = field(default_factory=dict)
    spikes: Mapping[str, tuple[int, ...]] = field(default_factory=dict)

    @property
    def empty(self) -> bool:
        return not self.columns and not self.channel_taxels


def build_demand(
    subscriptions: Iterable[Subscription],
    n_taxels: int,
    allowed_classes: Sequence[str],
    decoder_classes: Mapping[str, Sequence[str]],
    taxels_of: Callable[[Subscription], np.ndarray | None] | None = None,
) -> Demand:
    """Union of the subscriptions, limited to existing taxels and the classes the service may compute
    (a subscription's ``classes`` None: all of those). A decoded-output subscription adds the classes
    its decoders read (``decoder_classes[name]``). ``taxels_of(sub)``: the ids of the taxels ``sub``
    names (None: every taxel); by default its ``taxels`` and ``region`` without taxel positions
    (:meth:`~touchreal_client.protocol.Subscription.taxel_ids`: rectangles select nothing)."""
    pick = taxels_of or (lambda sub: sub.taxel_ids(n_taxels))
    cols = {c: np.zeros(n_taxels, bool) for c in CLASSES}
    spikes = {c: np.zeros(n_taxels, bool) for c in CLASSES}
    chan = np.zeros(n_taxels, bool)
    decs: dict[str, np.ndarray] = {}
    for sub in subscriptions:
        ids = pick(sub)
        taxels = slice(None) if ids is None else ids[ids < n_taxels]
        if "spikes" in sub.streams:
            for c in allowed_classes if sub.classes is None else sub.classes:
                cols[c][taxels] = True
                spikes[c][taxels] = True
        if "channels" in sub.streams:
            chan[taxels] = True
        if "decoded" in sub.streams:
            for name in decoder_classes if sub.decoders is None else sub.decoders:
                if name in decoder_classes:
                    decs.setdefault(name, np.zeros(n_taxels, bool))[taxels] = True
                    for c in decoder_classes[name]:
                        cols[c][taxels] = True
    columns = {c: _ids(m) for c, m in cols.items() if m.any() and c in allowed_classes}
    decoders = {n: _ids(m) for n, m in decs.items() if all(c in columns for c in decoder_classes[n])}
    wanted = {c: _ids(m) for c, m in spikes.items() if m.any() and c in allowed_classes}
    return Demand(columns, _ids(chan), decoders, wanted)


def _ids(mask: np.ndarray) -> tuple[int, ...]:
    return tuple(np.flatnonzero(mask).tolist())
