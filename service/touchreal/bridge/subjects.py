"""Where one sensor's stream lives on the broker (all under ``touchreal.<sensor_id>.``).

* ``frames``: binary spikes frames (docs/stream-protocol.md), one per update, all demanded classes
  and taxels; header ``seq`` = the publisher's sequence on this subject (a jump = frames lost),
  ``dropped`` = frames the publisher itself could not publish; NATS header :data:`SESSION_HEADER`
  = the service's session.
* ``channels``: binary channels frames at full rate (decimation 1) for the taxels some gateway
  wants, one per update, with their own ``seq``; only while demanded.
* ``hello``: the service's ``hello`` JSON; a request (any payload, with a reply subject) is answered
  with the current one, and the publisher announces a new one here when it changes.
* ``demand``: JSON demand announcements of the gateways (:mod:`.demand`).
"""

from __future__ import annotations

import re

SESSION_HEADER = "Touchreal-Session"
_SENSOR_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def check_sensor_id(sensor_id: str) -> str:
    """A sensor id is one NATS subject token: letters, digits, ``_`` and ``-`` (1..64)."""
    if not _SENSOR_ID.match(sensor_id):
        raise ValueError(f"sensor id {sensor_id!r}: use 1-64 letters, digits, '_' or '-' (it is a NATS subject token)")
    return sensor_id


def frames(sensor_id: str) -> str:
    return f"touchreal.{sensor_id}.frames"


def channels(sensor_id: str) -> str:
    return f"touchreal.{sensor_id}.channels"


def hello(sensor_id: str) -> str:
    return f"touchreal.{sensor_id}.hello"


def demand(sensor_id: str) -> str:
    return f"touchreal.{sensor_id}.demand"
