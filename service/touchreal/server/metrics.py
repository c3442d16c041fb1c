"""Prometheus metrics of one service (its own registry, served at ``/metrics``)."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram
from prometheus_client.core import HistogramMetricFamily
from prometheus_client.utils import floatToGoString

from touchreal_client.protocol import CLASSES

from .hub import DROP_REASONS

AUTH_OUTCOMES = ("failure", "throttled")
_LATENCY_BUCKETS = (0.005, 0.01, 0.02, 0.03, 0.05, 0.075, 0.1, 0.125, 0.15, 0.175, 0.2, 0.25, 0.3, 0.5, 1.0)
_COMPUTE_BUCKETS = (0.0001, 0.00025, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1)


class SpikeLatency:
    """A histogram with one label (the afferent class) observed a whole update's spikes at a time:
    prometheus_client's :class:`~prometheus_client.Histogram` takes one value per call (about 1.5 us
    with its label lookup), and a large skin's service sends some 100,000 spikes a second: ~0.15 s per s
    of the event loop's time (and of the GIL the encoder needs). Exposed as a
    prometheus_client collector in the same text as a Histogram's (cumulative ``le`` buckets, +Inf,
    sum and count)."""

    def __init__(self, name: str, documentation: str, labelnames: Sequence[str], registry: CollectorRegistry,
                 buckets: Sequence[float], label_values: Sequence[str] = CLASSES):
        if tuple(labelnames) != ("cls",):
            raise ValueError("SpikeLatency has the one label cls")
        self.name, self.documentation = name, documentation
        self.bounds = np.asarray(sorted(buckets), np.float64)  #: upper bounds (s); +Inf follows
        self._counts = {v: np.zeros(self.bounds.size + 1, np.int64) for v in label_values}
        self._sums = dict.fromkeys(label_values, 0.0)
        self._lock = threading.Lock()
        registry.register(self)

    def observe(self, label: str, values: np.ndarray) -> None:
        """Count ``values`` (s) under ``label``: each in the first bucket whose bound it does not exceed
        (as ``Histogram.observe``); non-finite values are not counted."""
        v = np.asarray(values, np.float64).ravel()
        v = v[np.isfinite(v)]
        if not v.size:
            return
        counts = np.bincount(np.searchsorted(self.bounds, v, side="left"), minlength=self.bounds.size + 1)
        with self._lock:
            if label not in self._counts:
                self._counts[label], self._sums[label] = np.zeros_like(counts), 0.0
            self._counts[label] += counts
            self._sums[label] += float(v.sum())

    def describe(self) -> list[HistogramMetricFamily]:
        return [HistogramMetricFamily(self.name, self.documentation, labels=["cls"])]

    def collect(self) -> Iterator[HistogramMetricFamily]:
        family = HistogramMetricFamily(self.name, self.documentation, labels=["cls"])
        les = [floatToGoString(b) for b in self.bounds] + ["+Inf"]
        with self._lock:
            for label, counts in self._counts.items():
                family.add_metric([label], list(zip(les, np.cumsum(counts).tolist())), self._sums[label])
        yield family


#: Every metric of a service: attribute of :class:`Metrics` -> (type, name, help, label names). Counters
#: are exported with ``_total`` after the name; histograms take their buckets from :data:`_BUCKETS`.
METRICS: dict[str, tuple[type, str, str, tuple[str, ...]]] = {
    "compute": (Histogram, "touchreal_update_compute_seconds", "encoder compute time per update", ()),
    "latency": (SpikeLatency, "touchreal_latency_seconds", "end-to-end latency per spike: acquisition of the sample "
                "that caused it to its update leaving the encoder", ("cls",)),
    "events": (Counter, "touchreal_events", "spike events encoded", ("cls",)),
    "updates": (Counter, "touchreal_updates", "updates published", ()),
    "overload": (Counter, "touchreal_updates_dropped_overload", "updates dropped because the event loop fell "
                 "behind the acquisition thread", ()),
    "shed_seconds": (Counter, "touchreal_shed_seconds", "seconds of signal acquired but not encoded because "
                     "compute fell more than max_lag_ms behind acquisition", ()),
    "sheds": (Counter, "touchreal_sheds", "sheds (each a seq gap for every subscriber and a restart of the "
              "pipeline from rest)", ()),
    "lag": (Gauge, "touchreal_acquisition_lag_seconds", "age of the latest chunk's oldest sample when its "
            "compute started (clock model)", ()),
    "real_time_factor": (Gauge, "touchreal_real_time_factor", "wall time spent per second of signal encoded, "
                         "about 1 s average (< 1 keeps up)", ()),
    "awake": (Gauge, "touchreal_taxels_awake", "taxels the encoder runs (a contact woke them, or their channels "
              "are wanted; all of them when dense)", ()),
    "clients": (Gauge, "touchreal_clients_connected", "connected stream clients", ()),
    "client_drops": (Gauge, "touchreal_client_dropped_frames", "frames dropped for a connected client", ("client",)),
    "drops": (Counter, "touchreal_dropped_frames", "frames dropped for clients, connected or gone (queue_full: "
              "the client's queue was full; stale: it waited longer than max_frame_age_ms; upstream_loss: lost on a "
              "gateway's broker hop or shed by an overloaded pipeline)", ("reason",)),
    "kicked": (Counter, "touchreal_clients_closed_slow", "clients closed as slow consumers (4008)", ()),
    "flooding": (Counter, "touchreal_clients_closed_flooding", "clients closed for sending requests faster than "
                 "they read the replies (4029)", ()),
    "faults": (Gauge, "touchreal_input_faults", "cumulative input faults (sanitizer: NaN/Inf, gaps, ...; "
               "serial: CRC errors, gaps, resyncs, reconnects)", ("kind",)),
    "auth": (Counter, "touchreal_auth_refused", "write requests refused at authentication (failure: a wrong "
             "or missing token; throttled: 429 to a peer in back-off after repeated failures)", ("outcome",)),
    "source_state": (Gauge, "touchreal_source_state", "1 for the source's current state", ("state",)),
    "ready": (Gauge, "touchreal_ready", "1 when the source delivers and the pipeline is warm", ()),
}
#: Buckets (s) of the histograms.
_BUCKETS = {"compute": _COMPUTE_BUCKETS, "latency": _LATENCY_BUCKETS}
#: Label values a metric exports from the start (at 0), before any of them occurs.
_KNOWN_LABELS = {"events": CLASSES, "drops": DROP_REASONS, "auth": AUTH_OUTCOMES}


class Metrics:
    """The metrics of :data:`METRICS`, each the attribute of its key, in a registry of their own."""

    compute: Histogram
    latency: SpikeLatency
    events: Counter
    updates: Counter
    overload: Counter
    shed_seconds: Counter
    sheds: Counter
    lag: Gauge
    real_time_factor: Gauge
    awake: Gauge
    clients: Gauge
    client_drops: Gauge
    drops: Counter
    kicked: Counter
    flooding: Counter
    faults: Gauge
    auth: Counter
    source_state: Gauge
    ready: Gauge

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        for attr, (kind, name, doc, labels) in METRICS.items():
            buckets = {"buckets": _BUCKETS[attr]} if attr in _BUCKETS else {}
            setattr(self, attr, kind(name, doc, labels, registry=self.registry, **buckets))
        for attr, values in _KNOWN_LABELS.items():
            for value in values:
                getattr(self, attr).labels(value)

    def follow(self, runtime: Callable[[], Any]) -> None:
        """Read the acquisition lag, the real-time factor and the taxels awake from ``runtime()`` (the current
        :class:`~.runtime.Runtime` or None) whenever the metrics are collected."""
        self.lag.set_function(lambda: getattr(runtime(), "lag_s", 0.0))
        self.real_time_factor.set_function(lambda: getattr(runtime(), "real_time_factor", 0.0))
        self.awake.set_function(lambda: getattr(getattr(runtime(), "encoder", None), "awake_taxels", 0))

    def count_drop(self, reason: str, frames: int) -> None:
        """A hub's ``on_drop``: frames dropped for a client, by reason."""
        self.drops.labels(reason).inc(frames)

    def count_auth(self, outcome: str) -> None:
        """A body guard's ``on_auth``: one refused write, by outcome (:data:`AUTH_OUTCOMES`)."""
        self.auth.labels(outcome).inc()
