"""The service's metrics (server/metrics.py)."""

from __future__ import annotations

import numpy as np
import pytest
from prometheus_client import CollectorRegistry, Histogram, generate_latest

from touchreal.server.metrics import Metrics, SpikeLatency


def _samples(registry: CollectorRegistry) -> tuple[list[str], dict[str, float]]:
    """(bucket and count lines, sum per label) of the exposition (a Histogram's ``_created`` aside)."""
    lines = [line for line in generate_latest(registry).decode().splitlines()
             if not line.startswith("#") and "_created" not in line]
    sums = {line.split(" ")[0]: float(line.split(" ")[1]) for line in lines if "_sum{" in line}
    return [line for line in lines if "_sum{" not in line], sums


def _same(mine: CollectorRegistry, ref: CollectorRegistry) -> None:
    (lines, sums), (ref_lines, ref_sums) = _samples(mine), _samples(ref)
    assert lines == ref_lines and len(lines) > 10
    assert sums.keys() == ref_sums.keys() and all(sums[k] == pytest.approx(ref_sums[k], rel=1e-12) for k in sums)


def test_spike_latency_exposes_what_a_histogram_observing_each_spike_would():
    """Whole arrays observed at once give prometheus_client's Histogram exposition, spike for spike:
    values on a bucket's bound count in it, values past the last bound only in +Inf, sums add up (to
    the rounding of their order)."""
    buckets = (0.005, 0.01, 0.02, 0.05, 0.1)
    mine, ref = CollectorRegistry(), CollectorRegistry()
    latency = SpikeLatency("x_latency_seconds", "doc", ("cls",), mine, buckets, label_values=("SA1", "RA"))
    hist = Histogram("x_latency_seconds", "doc", ("cls",), registry=ref, buckets=buckets)
    rng = np.random.default_rng(0)
    for label in ("SA1", "RA", "SA1"):
        values = np.concatenate([rng.exponential(0.02, 500), np.array(buckets), [0.0, 0.3, 2.5]])
        latency.observe(label, values)
        for v in values:
            hist.labels(label).observe(float(v))
    _same(mine, ref)
    latency.observe("SA1", np.array([np.nan, np.inf]))  # not counted (nor in the sum)
    _same(mine, ref)


def test_the_service_latency_histogram_lists_every_class_from_the_start():
    text = generate_latest(Metrics().registry).decode()
    for c in ("SA1", "RA", "PC"):
        assert f'touchreal_latency_seconds_count{{cls="{c}"}} 0.0' in text
        assert f'touchreal_latency_seconds_bucket{{cls="{c}",le="+Inf"}} 0.0' in text


def test_spike_latency_takes_only_its_one_label():
    with pytest.raises(ValueError, match="one label"):
        SpikeLatency("y", "doc", ("cls", "taxel"), CollectorRegistry(), (0.1,))
