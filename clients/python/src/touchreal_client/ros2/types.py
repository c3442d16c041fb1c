"""The ROS 2 message types of TouchReal's topics in rosbags' type system (extra ``ros2``): ROS 2's
standard types (``std_msgs``, ``builtin_interfaces``) plus ``touchreal_msgs`` parsed from its ``.msg``
files (:data:`.messages.MSG_PACKAGE`). The rosbag2 export serialises with it; the DDS bridge builds
its cyclonedds types and type hashes from it."""

from __future__ import annotations

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from .messages import msg_definitions


def typestore() -> Typestore:
    """A fresh typestore: ROS 2 Jazzy's standard types (whose ``std_msgs`` and ``builtin_interfaces``
    are Humble's too) and ``touchreal_msgs``."""
    store = get_typestore(Stores.ROS2_JAZZY)
    ours: dict = {}
    for name, text in msg_definitions().items():
        ours.update(get_types_from_msg(text, name))
    store.register(ours)
    return store
