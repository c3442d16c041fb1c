"""The JSON topics TouchReal gives other tools, shared by the MCAP recorder (:mod:`.record`) and the
Foxglove live view (:mod:`.bridges.foxglove`) so one Foxglove layout serves a recording and the live
stream: topic names and the JSON Schemas of their messages (one message per spike, per channel
sample, per decoder step). Light: numpy and the protocol only.

* ``/touchreal/spikes/<CLASS>``: ``t_us`` (wire clock, integer us), ``taxel``, ``class``;
* ``/touchreal/channels``: ``t_us`` and per taxel of ``taxels`` ``ST`` [N], ``dST`` [N/s], ``PVDF`` [V], ``dPVDF`` [V/s];
* ``/touchreal/force``: ``t_us``, ``taxels``, ``force_N`` (the ST channel; the live view's);
* ``/touchreal/decoded/<DECODER>``: ``t_us`` (end of the window), ``taxels``, ``outputs`` (names), ``values[taxel][output]``;
* ``/touchreal/clock``: the stream's clock points.

Every data message also carries its frame's ``update`` and ``params_rev``; NaN is sent as null.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from . import protocol as P

PROFILE = "touchreal"  #: the MCAP profile of a TouchReal recording (:mod:`.record` writes it, :mod:`.session` checks it)
PREFIX = "/touchreal"
CLOCK_TOPIC = f"{PREFIX}/clock"
CHANNELS_TOPIC = f"{PREFIX}/channels"
FORCE_TOPIC = f"{PREFIX}/force"
SPIKES_PREFIX = f"{PREFIX}/spikes/"
DECODED_PREFIX = f"{PREFIX}/decoded/"


def spikes_topic(cls: str) -> str:
    return SPIKES_PREFIX + cls


def decoded_topic(name: str) -> str:
    return DECODED_PREFIX + name


def _schema(title: str, description: str, props: dict[str, Any]) -> dict[str, Any]:
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": title, "description": description,
            "type": "object", "properties": props, "required": list(props)}


_INT = {"type": "integer", "minimum": 0}
_NUM_OR_NULL = {"type": ["number", "null"]}
_TAXELS = {"type": "array", "items": _INT}
_FRAME = {"update": {**_INT, "description": "server update counter"},
          "params_rev": {**_INT, "description": "parameter revision that made it"}}
SPIKE_SCHEMA = _schema("touchreal.Spike", "one afferent spike", {
    "t_us": {**_INT, "description": "stamp on the wire clock (us)"},
    "taxel": _INT, "class": {"enum": list(P.CLASSES)}, **_FRAME})
CHANNELS_SCHEMA = _schema("touchreal.Channels", "one 5 kHz grid sample of the preprocessed channels, per taxel", {
    "t_us": {**_INT, "description": "sample time on the wire clock (us)"},
    "taxels": _TAXELS,
    **{c: {"type": "array", "items": _NUM_OR_NULL, "description": f"per taxel, {u}"} for c, u in zip(P.CHANNELS, P.CHANNEL_UNITS)},
    **_FRAME})
FORCE_SCHEMA = _schema("touchreal.Force", "one sample of the preprocessed force (the ST channel), per taxel", {
    "t_us": {**_INT, "description": "sample time on the wire clock (us)"},
    "taxels": _TAXELS,
    "force_N": {"type": "array", "items": _NUM_OR_NULL, "description": "per taxel, N"},
    **_FRAME})
DECODED_SCHEMA = _schema("touchreal.Decoded", "one decoder step", {
    "t_us": {**_INT, "description": "end of the decoding window on the wire clock (us)"},
    "taxels": _TAXELS,
    "outputs": {"type": "array", "items": {"type": "string"}},
    "values": {"type": "array", "items": {"type": "array", "items": _NUM_OR_NULL},
               "description": "values[taxel][output]; null = NaN (window not yet filled)"},
    **_FRAME})
CLOCK_SCHEMA = _schema("touchreal.Clock", "the stream's clock point: wall(t) = wall_us + (t - sensor_us) * rate", {
    "type": {"const": "clock"}, "sensor_us": _INT, "wall_us": _INT, "rate": {"type": "number"},
    "error_us": _INT, "epoch": _INT})


def json_lists(a: np.ndarray) -> list[Any]:
    """A float array as nested lists for JSON (NaN -> None)."""
    v = a.astype(np.float64)
    if np.isfinite(v).all():
        return v.tolist()
    return np.where(np.isfinite(v), v, None).tolist()


def wanted_subscription(topics: Iterable[str], decimation: int = 25, hello: dict | None = None) -> P.Subscription:
    """The upstream subscription that feeds exactly ``topics`` (nothing at all for none). From a
    ``hello`` whose ids are a population's afferents, only the spike topics are fed (a population has
    no channels or decoders), so a channel topic never gets the spikes refused along with it."""
    topics = set(topics)
    if hello is not None and P.hello_afferents(hello) is not None:
        topics = {t for t in topics if t.startswith(SPIKES_PREFIX)}
    classes = [c for c in P.CLASSES if spikes_topic(c) in topics]
    decoders = sorted(t[len(DECODED_PREFIX):] for t in topics if t.startswith(DECODED_PREFIX))
    streams = [s for s, on in (("spikes", bool(classes)), ("channels", bool(topics & {CHANNELS_TOPIC, FORCE_TOPIC})),
                               ("decoded", bool(decoders))) if on]
    return P.Subscription(taxels=None, classes=classes, streams=streams, decimation=decimation,
                          decoders=decoders or None)
