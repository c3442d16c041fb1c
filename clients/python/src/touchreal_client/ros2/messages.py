"""TouchReal's ROS 2 topics and their messages as plain field values (sans-I/O, numpy only).

The live DDS bridge (:mod:`touchreal_client.bridges.ros2`) and the rosbag2 export
(:mod:`touchreal_client.ros2.rosbag2`) both build their messages from these: one function per message
type turns a stream frame into a dict keyed by the ROS field names of ``touchreal_msgs`` (the package
beside this module, :data:`MSG_PACKAGE`), with numpy arrays for array fields and nested dicts for
``std_msgs/Header`` and ``builtin_interfaces/Time``. Each transport then makes its own typed message.

Stamps: ``to_local_ns`` maps wire-clock stamps (us, an array) to the publisher's clock in integer
nanoseconds since the Unix epoch — by the stream's clock model live, by the recorded clock points in
an export. ROS topic names are given without the DDS ``rt`` prefix.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from .. import protocol as P

#: The colcon-buildable ROS 2 package of TouchReal's message definitions (``msg/*.msg``).
MSG_PACKAGE = Path(__file__).resolve().parent / "touchreal_msgs"
#: ROS 2 type names of the messages, as rosbags and ``ros2 topic`` spell them.
SPIKES_TYPE = "touchreal_msgs/msg/Spikes"
CHANNELS_TYPE = "touchreal_msgs/msg/Channels"
FORCE_TYPE = "touchreal_msgs/msg/Force"
DECODED_TYPE = "touchreal_msgs/msg/Decoded"
DESCRIPTION_TYPE = "std_msgs/msg/String"

FRAME_ID = "touchreal"
DESCRIPTION_TOPIC = "/touchreal/description"
CHANNELS_TOPIC = "/touchreal/channels"
FORCE_TOPIC = "/touchreal/force"

ToLocalNs = Callable[[np.ndarray], np.ndarray]


def spikes_topic(cls: str) -> str:
    return f"/touchreal/spikes/{cls}"


def decoded_topic(name: str) -> str:
    return f"/touchreal/decoded/{name}"


def msg_definitions() -> dict[str, str]:
    """ROS type name -> the text of its ``.msg`` file, for every message of :data:`MSG_PACKAGE`."""
    return {f"touchreal_msgs/msg/{p.stem}": p.read_text() for p in sorted((MSG_PACKAGE / "msg").glob("*.msg"))}


def time_of_ns(ns: int) -> dict[str, int]:
    """``builtin_interfaces/Time`` of a stamp in integer ns (``sec`` int32, ``nanosec`` uint32)."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return {"sec": sec, "nanosec": nanosec}


def header(stamp_ns: int) -> dict[str, Any]:
    return {"stamp": time_of_ns(stamp_ns), "frame_id": FRAME_ID}


def _local_ns(to_local_ns: ToLocalNs, t_us: np.ndarray) -> np.ndarray:
    return np.atleast_1d(np.asarray(to_local_ns(np.asarray(t_us, np.int64)), np.int64))


def spikes(frame: P.SpikesFrame, cls: str, to_local_ns: ToLocalNs) -> dict[str, Any] | None:
    """The ``Spikes`` message of class ``cls`` in ``frame``; None when the frame has neither a spike
    of that class nor a finality for it (nothing to say). ``header.stamp`` is the local time of
    ``final_us``, or of the last spike when the frame has no finality for the class (then
    ``final_us`` is -1)."""
    k = P.CLASSES.index(cls)
    mine = frame.cls == k
    t_us = frame.t_us[mine].astype(np.int64)
    final = frame.final_us.get(cls)
    if final is None and t_us.size == 0:
        return None
    final_us = int(final) if final is not None else -1
    stamps = _local_ns(to_local_ns, np.append(t_us, final_us if final is not None else t_us.max()))
    sec, nanosec = np.divmod(stamps[:-1], 1_000_000_000)
    return {"header": header(int(stamps[-1])), "afferent_class": cls, "update": int(frame.header.update),
            "params_rev": int(frame.header.params_rev), "final_us": final_us, "t_us": t_us,
            "stamps": [{"sec": int(s), "nanosec": int(n)} for s, n in zip(sec, nanosec)],
            "taxel": frame.taxel[mine].astype(np.uint32)}


def _block(frame: P.ChannelsFrame, to_local_ns: ToLocalNs) -> dict[str, Any]:
    stamp = int(_local_ns(to_local_ns, np.array([frame.t0_us]))[0])
    return {"header": header(stamp), "update": int(frame.header.update), "params_rev": int(frame.header.params_rev),
            "t0_us": int(frame.t0_us), "period_us": int(frame.period_us), "taxels": frame.taxels.astype(np.uint32),
            "samples": int(frame.data.shape[0])}


def channels(frame: P.ChannelsFrame, to_local_ns: ToLocalNs) -> dict[str, Any]:
    """The ``Channels`` message of a channels frame (every channel of every taxel)."""
    return {**_block(frame, to_local_ns), "channels": list(P.CHANNELS), "units": list(P.CHANNEL_UNITS),
            "data": np.ascontiguousarray(frame.data, np.float32).reshape(-1)}


def force(frame: P.ChannelsFrame, to_local_ns: ToLocalNs) -> dict[str, Any]:
    """The ``Force`` message of a channels frame (its ST channel)."""
    st = P.CHANNELS.index("ST")
    return {**_block(frame, to_local_ns), "force_n": np.ascontiguousarray(frame.data[:, :, st], np.float32).reshape(-1)}


def decoded(name: str, outputs: list[str], frame: P.DecodedFrame, to_local_ns: ToLocalNs) -> list[dict[str, Any]]:
    """One ``Decoded`` message per step of a decoded frame of the decoder ``name``."""
    stamps = _local_ns(to_local_ns, frame.t_us)
    taxels = frame.taxels.astype(np.uint32)
    return [{"header": header(int(ns)), "decoder": name, "update": int(frame.header.update),
             "params_rev": int(frame.header.params_rev), "t_us": int(t), "outputs": list(outputs), "taxels": taxels,
             "values": np.ascontiguousarray(frame.values[s], np.float64).reshape(-1)}
            for s, (t, ns) in enumerate(zip(frame.t_us.tolist(), stamps.tolist()))]


def description(hello: dict[str, Any]) -> dict[str, Any]:
    """The latched ``std_msgs/String`` of the stream's hello (JSON), for ``/touchreal/description``."""
    return {"data": json.dumps(hello, separators=(",", ":"), sort_keys=True)}
