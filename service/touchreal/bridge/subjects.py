"""Where one sensor's stream lives on the broker (all under ``touchreal.<sensor_id>.``).

* ``frames``: binary spikes frames (docs/stream-protocol.md), one per update, all demanded classes
  and taxels; header ``seq`` = the publisher's sequence on this subject (a jump = frames lost),
  ``dropped`` = frames the publisher itself could not publish; NATS header :data:`SESSION_HEADER`
  = the service's session.
* ``channels``: binary channels frames at full rate (decimation 1) for the taxels some gateway
  wants, one per update, with their own ``seq``; only while demanded.
* ``decoded.<name>``: binary decoded frames of decoder ``<name>`` for the taxels some gateway wants,
  with their own ``seq`` per decoder (a jump = that decoder's frames lost); only while demanded, and
  only for decoders whose name is one subject token (:func:`token_ok`).
* ``hello``: the publisher announces the service's ``hello`` JSON here when it changes.
* ``hello.request``: a request (any payload, with a reply subject) is answered with the current
  hello. Requests and announcements have their own subjects so broker permissions can let gateways
  ask without letting them announce (deploy/nats/nats-server.conf).
* ``demand.<gateway_id>``: the JSON demand announcements of gateway ``<gateway_id>`` (:mod:`.demand`).
  The sender is the subject's last token, so the broker can bind it: a gateway's credentials may
  publish on its own demand subject only (:func:`gateway_permissions`).
* ``decoders.request``: answered with the service's ``GET /v1/decoders`` JSON; ``model.request``
  (payload: a decoder name) with that model's ONNX bytes, or an empty reply with header
  :data:`ERROR_HEADER` naming why not. So a gateway serves the decoder routes too.
* ``clock``: the service's ``clock`` messages (its clock model), as it tells its own clients.

A frame over the broker's ``max_payload`` goes in parts with the header ``Touchreal-Part: k/n``
(:mod:`.parts`).

With ``--retain-s`` the frame subjects are also kept, for that many seconds, in the in-memory
JetStream stream :func:`stream_name`.
"""

from __future__ import annotations

import re
from collections.abc import Callable

SESSION_HEADER = "Touchreal-Session"
ERROR_HEADER = "Touchreal-Error"
_TOKEN = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def token_ok(name: str) -> bool:
    """``name`` can be one NATS subject token: letters, digits, ``_`` and ``-`` (1..64)."""
    return bool(_TOKEN.match(name))


def _check_token(what: str, name: str) -> str:
    """``name`` if it is one subject token, else ValueError naming ``what`` it is."""
    if not token_ok(name):
        raise ValueError(f"{what} {name!r}: use 1-64 letters, digits, '_' or '-' (it is a NATS subject token)")
    return name


def check_sensor_id(sensor_id: str) -> str:
    """A sensor id is one NATS subject token (:func:`token_ok`)."""
    return _check_token("sensor id", sensor_id)


def check_gateway_id(gateway_id: str) -> str:
    """A gateway id is one NATS subject token (:func:`token_ok`)."""
    return _check_token("gateway id", gateway_id)


def subject(sensor_id: str, *tokens: str) -> str:
    """``touchreal.<sensor_id>.<tokens...>``: a subject of one sensor."""
    return ".".join(("touchreal", sensor_id, *tokens))


def _leaf(*tokens: str) -> Callable[[str], str]:
    """A function of a sensor id giving its subject ``touchreal.<sensor_id>.<tokens...>``."""
    return lambda sensor_id: subject(sensor_id, *tokens)


frames = _leaf("frames")
channels = _leaf("channels")
hello = _leaf("hello")
hello_request = _leaf("hello", "request")
clock = _leaf("clock")
decoders_request = _leaf("decoders", "request")
model_request = _leaf("model", "request")
demand_any = _leaf("demand", "*")  #: the wildcard the publisher subscribes to: every gateway's demand subject
decoded_any = _leaf("decoded", "*")  #: the wildcard a gateway subscribes to: every decoder's subject


def demand(sensor_id: str, gateway_id: str) -> str:
    """Where gateway ``gateway_id`` announces its demand (and nobody else may, on a broker with
    :func:`gateway_permissions`)."""
    return subject(sensor_id, "demand", gateway_id)


def decoded(sensor_id: str, decoder: str) -> str:
    """Where decoder ``decoder``'s outputs are published."""
    return subject(sensor_id, "decoded", decoder)


def last_token(subject: str) -> str:
    """The last token of a subject: the decoder of ``decoded.<name>``, the gateway of ``demand.<id>``."""
    return subject.rsplit(".", 1)[1]


def retained(sensor_id: str) -> list[str]:
    """The subjects a retaining publisher keeps (every frame subject; not hello or demand)."""
    return [frames(sensor_id), channels(sensor_id), decoded_any(sensor_id)]


def gateway_permissions(gateway_id: str) -> dict[str, list[str]]:
    """The broker permissions of gateway ``gateway_id``, for every sensor: its own demand subject, the
    requests, and reading frames, hello, clock and request replies (deploy/nats/nats-server.conf)."""
    return {"publish": [demand("*", gateway_id), hello_request("*"), decoders_request("*"), model_request("*")],
            "subscribe": [frames("*"), channels("*"), decoded_any("*"), hello("*"), clock("*"), "_INBOX.>"]}


def stream_name(sensor_id: str) -> str:
    """The JetStream stream that keeps a sensor's last seconds (``--retain-s``)."""
    return f"touchreal_{sensor_id}"
