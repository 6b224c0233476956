"""The rosbags type stores used to serialize, convert and describe recorded messages.

ROS 2 messages are CDR against ROS 2 Humble's definitions (and ours, ``wavegrasp_msgs``);
ROS 1 bags use ROS 1 Noetic's definitions (whose `std_msgs/Header` carries a `seq` field that
CDR drops), completed by Humble's.
"""

from __future__ import annotations

from functools import cache

from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from wavegrasp.schemas.ros import typestore


def ros2_typestore() -> Typestore:
    """Return the shared ROS 2 Humble type store (CDR, ros2msg definitions), our own
    ``wavegrasp_msgs`` types registered in it."""
    return typestore()


@cache
def ros1_typestore() -> Typestore:
    """Return the shared ROS 1 type store (ROS 1 bags' definitions and md5sums).

    ROS 1 Noetic's types, plus ROS 2 Humble's for packages Noetic's store lacks (tf2_msgs).
    """
    store = get_typestore(Stores.EMPTY)
    noetic = get_typestore(Stores.ROS1_NOETIC)
    store.register({**ros2_typestore().fielddefs, **noetic.fielddefs})
    return store


def check_msgtype(msgtype: str, store: Typestore) -> None:
    """Raise ValueError if `store` does not know `msgtype` (e.g. 'sensor_msgs/msg/PointCloud2')."""
    if msgtype not in store.fielddefs:
        raise ValueError(f"unknown message type {msgtype!r} (not in the rosbags type store)")


@cache
def ros2_msgdef(msgtype: str) -> str:
    """Return the ros2msg schema text of `msgtype`, as ROS 2 writers store it in MCAP.

    Parameters
    ----------
    msgtype : str
        ROS 2 type name, e.g. 'sensor_msgs/msg/PointCloud2'.

    Returns
    -------
    str
        The type's definition followed by those of its dependencies, each introduced by a line of
        80 '=' and 'MSG: pkg/Type' (rosbags' ``generate_msgdef(..., ros_version=2)``).

    Raises
    ------
    ValueError
        If the type is not one of ROS 2 Humble's.
    """
    store = ros2_typestore()
    check_msgtype(msgtype, store)
    return store.generate_msgdef(msgtype, ros_version=2)[0]
