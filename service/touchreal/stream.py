"""Online encoding as one state machine: raw chunks in, spike events out, computed on demand.

:class:`StreamEncoder` chains the :class:`~touchreal.preprocess.pipeline.Preprocessor` and one
:class:`~touchreal.encoding.encoder.Encoder` per *source* (the PVDF window a group of classes
reads, or the SingleTact alone for classes whose PVDF and dPVDF weights are all zero). The
service, the replay player, the ``encode`` command, the tests and the benchmarks all drive this
same object; offline encoding is the same object fed once.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from .encoding.encoder import Encoder, SpikeEvents
from .params import EncoderParams
from .preprocess.pipeline import Channels, Preprocessor, Source
from .recording import Trial
from .sensing.raw import RawChunk
from .sensing.replay import ReplaySource
from .settings import CLASSES, OUT_FS_HZ

_PVDF_WEIGHTS = slice(4, 8)  #: PVDF+, PVDF-, dPVDF+, dPVDF- in w1..w8


def class_source(params: EncoderParams, cls: str) -> Source:
    """The preprocessing source of a class: its causal window (ms), or None when all its PVDF and
    dPVDF weights are zero (it then reads the SingleTact channels alone and waits for no window)."""
    if not any(params.classes[cls].weights[_PVDF_WEIGHTS]):
        return None
    return float(params.window_ms(cls))


class StreamEncoder:
    """Raw samples of N taxels -> SA1/RA/PC spike events, chunk by chunk, for the active columns.

    ``classes`` are the classes this encoder can serve (default: all of the parameter set); all
    their (class, taxel) columns are active at first (:meth:`set_active` changes that). Every spike
    is stamped on the sensor clock, ``(k + 1) / 5000 + delay_ms`` for a threshold crossing at grid
    sample k, whenever it is emitted; each source emits as soon as its own branches allow.
    """

    def __init__(
        self, params: EncoderParams, n_taxels: int = 1, classes: Sequence[str] | None = None, dtype: type = np.float64
    ):
        wanted = tuple(params.classes) if classes is None else tuple(classes)
        missing = [c for c in wanted if c not in params.classes]
        if missing:
            raise ValueError(f"parameter set has no class {missing}")
        self.params = params
        self.n_taxels = n_taxels
        self.classes = tuple(c for c in CLASSES if c in wanted)
        self.source: dict[str, Source] = {c: class_source(params, c) for c in self.classes}
        groups: dict[Source, list[str]] = {}
        for c in self.classes:
            groups.setdefault(self.source[c], []).append(c)
        self.encoders = {s: Encoder(params, n_taxels, cs) for s, cs in groups.items()}
        windows = [s for s in groups if s is not None]
        self.pre = Preprocessor(
            params.preprocess, n_taxels, dtype, sources=list(groups), max_window_ms=max(windows, default=params.preprocess.window_ms)
        )
        self.active: dict[str, tuple[int, ...]] = {c: tuple(range(n_taxels)) for c in self.classes}
        self._delay_s = {c: params.classes[c].delay_ms / 1000.0 for c in self.classes}

    # -- demand ---------------------------------------------------------------------------------
    def set_active(self, columns: Mapping[str, Iterable[int]]) -> None:
        """Demand: per class, the taxels whose spikes are wanted (a class absent or with no taxels is off).

        * Continuing columns keep their state bit-exactly: a column's spikes never depend on which
          other columns, classes or windows run.
        * A column that (re)starts starts from rest (:class:`~touchreal.encoding.encoder.Encoder`)
          at the next grid sample its source delivers: for a source that kept running, the sample
          after the last one delivered; for a source that (re)starts, the first grid sample after
          the newest raw sample received (:meth:`Preprocessor.restart_index`).
        * A PVDF window branch runs only while an active column reads it; the PVDF filter only
          while some window runs; the SingleTact branch only while any column is active. A branch
          that restarts is rebuilt from the raw history acquisition keeps (no waiting: its class
          emits after its usual latency), see :meth:`Preprocessor.set_sources`.
        * With everything off, :meth:`process` only runs acquisition: the sanitizers (input
          policy and counters) and the raw history rings (the last 0.5 s of SingleTact, the last
          100 ms + two frames of the longest window of PVDF) that restarts are rebuilt from.
        """
        unknown = set(columns) - set(self.classes)
        if unknown:
            raise ValueError(f"classes {sorted(unknown)} are not served (have {list(self.classes)})")
        want = {c: tuple(sorted({int(x) for x in columns.get(c, ())})) for c in self.classes}
        bad = sorted({x for xs in want.values() for x in xs if not 0 <= x < self.n_taxels})
        if bad:
            raise ValueError(f"taxels {bad} out of range 0..{self.n_taxels - 1}")
        for enc in self.encoders.values():
            enc.set_columns({c: want[c] for c in enc.classes})
        self.pre.set_sources([s for s, enc in self.encoders.items() if enc.n_columns])
        self.active = {c: xs for c, xs in want.items() if xs}

    # -- data -----------------------------------------------------------------------------------
    def process(self, chunk: RawChunk) -> SpikeEvents:
        """Spikes of the active columns that became final with this chunk, sorted by time."""
        self.pre.feed(chunk.st_t, chunk.st, chunk.pvdf_t, chunk.pvdf)
        return self._encode()[1]

    def process_channels(self, chunk: RawChunk) -> tuple[Channels, SpikeEvents]:
        """Like :meth:`process`, also returning new 5 kHz channels (for dashboards and analysis): those
        of the active source with the longest window (:attr:`display_source`; its ST and dST are
        the SingleTact channels every source shares). Empty when no column is active."""
        self.pre.feed(chunk.st_t, chunk.st, chunk.pvdf_t, chunk.pvdf)
        return self._encode()

    def finish(self) -> SpikeEvents:
        """End of stream: flush every running branch and return the last spikes."""
        self.pre.flush()
        return self._encode()[1]

    def _encode(self) -> tuple[Channels, SpikeEvents]:
        shown = self.display_source
        channels = Channels(0, np.zeros((0, self.n_taxels, 4)))
        parts = []
        for s in self.pre.sources:
            ch = self.pre.take(s)
            parts.append(self.encoders[s].process(ch))
            if s == shown:
                channels = ch
        events = SpikeEvents.concatenate(parts)
        if len(parts) > 1:
            order = np.argsort(events.t_s, kind="stable")
            events = SpikeEvents(events.t_s[order], events.taxel[order], events.cls[order])
        return channels, events

    # -- reporting ------------------------------------------------------------------------------
    @property
    def display_source(self) -> Source | None:
        """The active source :meth:`process_channels` returns: the longest active window, else the
        SingleTact-only source (PVDF channels zero); None when nothing is active."""
        sources = self.pre.sources
        windows = [s for s in sources if s is not None]
        return max(windows) if windows else None

    @property
    def final_s(self) -> dict[str, float]:
        """Per active class: every spike of that class stamped before this time (s, sensor clock,
        delay included) has been returned (-inf before its source has started)."""
        out = {}
        for c in self.active:
            k = self.pre.cursor.get(self.source[c])
            out[c] = -np.inf if k is None else (k + 1) / OUT_FS_HZ + self._delay_s[c]
        return out

    @property
    def latency_s(self) -> dict[str, float]:
        """Per class: algorithmic latency, the upper bound of emission minus stamp (s) with
        ``delay_ms`` excluded (the look-ahead of the branches its source reads, less the one grid
        sample a spike's stamp is ahead of its sample); a spike's stamp moves by ``delay_ms``."""
        return {c: self.pre.latency_s(self.source[c]) - 1.0 / OUT_FS_HZ for c in self.classes}

    @property
    def stats(self) -> dict[str, dict[str, int]]:
        """Input-policy counters per sensor (see docs/architecture.md)."""
        return self.pre.stats

    def state_arrays(self) -> dict[str, np.ndarray]:
        """All state: preprocessing stages and buffers, class low-passes and membrane potentials."""
        out = dict(self.pre.state_arrays())
        for s, enc in self.encoders.items():
            name = "st" if s is None else f"{s:g}ms"
            out.update({f"{name}_{k}": a for k, a in enc.state_arrays().items()})
        return out

    def state_report(self) -> tuple[bool, float, int]:
        """(all finite, largest magnitude, total bytes) over :meth:`state_arrays`."""
        arrays = self.state_arrays().values()
        finite = all(bool(np.all(np.isfinite(a))) for a in arrays)
        peak = max((float(np.max(np.abs(a))) for a in arrays if a.size), default=0.0)
        return finite, peak, sum(a.nbytes for a in arrays)


def encode_chunks(
    params: EncoderParams, chunks: Iterable[RawChunk], n_taxels: int = 1, dtype: type = np.float64, classes: Sequence[str] | None = None
) -> SpikeEvents:
    """Encode a finite stream of chunks (flushing at the end), every class on its own window."""
    se = StreamEncoder(params, n_taxels, classes, dtype=dtype)
    parts = [se.process(c) for c in chunks]
    parts.append(se.finish())
    return SpikeEvents.concatenate(parts)


def encode_trial(
    trial: Trial, params: EncoderParams, update_s: float | None = None, dtype: type = np.float64, classes: Sequence[str] | None = None
) -> dict[str, np.ndarray]:
    """Spike times (s, recording clock) per class for one recorded trial, every class on its own window.

    ``update_s=None`` feeds the whole recording at once; otherwise it is replayed in chunks of
    ``update_s`` seconds. Both give identical spikes (one code path).
    """
    src = ReplaySource(trial)
    chunks = [src.read(trial.duration_s + 1.0)] if update_s is None else src.chunks(update_s)
    events = encode_chunks(params, chunks, dtype=dtype, classes=classes)
    return {c: events.train(c) for c in CLASSES if c in params.classes and (classes is None or c in classes)}
