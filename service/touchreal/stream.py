"""Online encoding as one state machine: raw chunks in, spike events out.

:class:`StreamEncoder` chains the :class:`~touchreal.preprocess.pipeline.Preprocessor` and the
:class:`~touchreal.encoding.encoder.Encoder`; the service, the replay player, the ``encode``
command, the tests and the benchmarks all drive this same object.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from .encoding.encoder import Encoder, SpikeEvents
from .params import EncoderParams
from .preprocess.pipeline import Channels, Preprocessor
from .recording import Trial
from .sensing.raw import RawChunk
from .sensing.replay import ReplaySource
from .settings import CLASSES, OUT_FS_HZ


class StreamEncoder:
    """Raw samples of N taxels -> SA1/RA/PC spike events, chunk by chunk."""

    def __init__(
        self, params: EncoderParams, n_taxels: int = 1, classes: Sequence[str] | None = None, dtype: type = np.float64
    ):
        self.params = params
        self.pre = Preprocessor(params.preprocess, n_taxels, dtype)
        self.enc = Encoder(params, n_taxels, classes)

    @property
    def latency_s(self) -> dict[str, float]:
        """Per class: algorithmic latency (s), emission minus stamp without the class delay."""
        return {c: self.pre.latency_s for c in self.params.classes}

    @property
    def final_s(self) -> dict[str, float]:
        """Per computed class: every spike stamped before this time (s) has been returned."""
        k = self.pre.align.next_k or 0
        return {c: k / OUT_FS_HZ + self.params.classes[c].delay_ms / 1000.0 for c in self.enc.classes}

    def set_active(self, columns: Mapping[str, Sequence[int]]) -> None:
        """Demand: per class, the taxels wanted. Classes leaving stop; a class (re)joining starts from
        rest. (Interim: whole classes, every taxel.)"""
        classes = [c for c in CLASSES if columns.get(c)]
        if tuple(classes) != self.enc.classes:
            self.enc = Encoder(self.params, self.pre.n_taxels, classes)

    def state_arrays(self) -> dict[str, np.ndarray]:
        """All state: preprocessing stages, class low-passes and membrane potentials."""
        return {**self.pre.state_arrays(), **self.enc.state_arrays()}

    def state_report(self) -> tuple[bool, float, int]:
        """(all finite, largest magnitude, total bytes) over :meth:`state_arrays`."""
        arrays = self.state_arrays().values()
        finite = all(bool(np.all(np.isfinite(a))) for a in arrays)
        peak = max((float(np.max(np.abs(a))) for a in arrays if a.size), default=0.0)
        return finite, peak, sum(a.nbytes for a in arrays)

    def process(self, chunk: RawChunk) -> SpikeEvents:
        ch = self.pre.process(chunk.st_t, chunk.st, chunk.pvdf_t, chunk.pvdf)
        return self.enc.process(ch)

    def process_channels(self, chunk: RawChunk) -> tuple[Channels, SpikeEvents]:
        """Like :meth:`process`, also returning the 5 kHz channels (for dashboards and analysis)."""
        ch = self.pre.process(chunk.st_t, chunk.st, chunk.pvdf_t, chunk.pvdf)
        return ch, self.enc.process(ch)

    def finish(self) -> SpikeEvents:
        return self.enc.process(self.pre.finish())


def encode_chunks(
    params: EncoderParams, chunks: Iterable[RawChunk], n_taxels: int = 1, dtype: type = np.float64
) -> SpikeEvents:
    """Encode a finite stream of chunks (flushing at the end)."""
    se = StreamEncoder(params, n_taxels, dtype=dtype)
    parts = [se.process(c) for c in chunks]
    parts.append(se.finish())
    return SpikeEvents.concatenate(parts)


def encode_trial(
    trial: Trial, params: EncoderParams, update_s: float | None = None, dtype: type = np.float64
) -> dict[str, np.ndarray]:
    """Spike times (s, recording clock) per class for one recorded trial.

    ``update_s=None`` feeds the whole recording at once; otherwise it is replayed in chunks of
    ``update_s`` seconds. Both give identical spikes (one code path).
    """
    src = ReplaySource(trial)
    chunks = [src.read(trial.duration_s + 1.0)] if update_s is None else src.chunks(update_s)
    events = encode_chunks(params, chunks, dtype=dtype)
    return {c: events.train(c) for c in CLASSES if c in params.classes}
