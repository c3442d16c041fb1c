"""What the connected subscribers need, as data: the pipeline computes exactly this.

A :class:`Demand` is immutable; the hub replaces it whenever a subscription changes and the
acquisition thread reads the current one once per update.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

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
) -> Demand:
    """Union of the subscriptions, limited to existing taxels and the classes the service may compute
    (a subscription's ``classes`` None: all of those). A decoded-output subscription adds the classes
    its decoders read (``decoder_classes[name]``)."""
    cols: dict[str, set[int]] = {c: set() for c in CLASSES}
    spikes: dict[str, set[int]] = {c: set() for c in CLASSES}
    chan: set[int] = set()
    decs: dict[str, set[int]] = {}
    for sub in subscriptions:
        taxels = set(range(n_taxels)) if sub.taxels is None else {t for t in sub.taxels if t < n_taxels}
        if "spikes" in sub.streams:
            for c in allowed_classes if sub.classes is None else sub.classes:
                cols[c] |= taxels
                spikes[c] |= taxels
        if "channels" in sub.streams:
            chan |= taxels
        if "decoded" in sub.streams:
            for name in decoder_classes if sub.decoders is None else sub.decoders:
                if name in decoder_classes:
                    decs.setdefault(name, set()).update(taxels)
                    for c in decoder_classes[name]:
                        cols[c] |= taxels
    columns = {c: tuple(sorted(t)) for c, t in cols.items() if t and c in allowed_classes}
    decoders = {n: tuple(sorted(t)) for n, t in decs.items() if all(c in columns for c in decoder_classes[n])}
    return Demand(columns, tuple(sorted(chan)), decoders,
                  {c: tuple(sorted(t)) for c, t in spikes.items() if t and c in allowed_classes})
