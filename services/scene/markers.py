"""ROS 2 messages of the scene (``visualization_msgs/msg/MarkerArray``,
``tf2_msgs/msg/TFMessage``, ``std_msgs/msg/String``) built from numpy arrays, as CDR.

Every field a message has is filled (rosbags' types have no defaults): what a caller does not
give is zero, empty or its type's own zero message. Positions are metres, frame as named.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from rosbags.typesys.store import Typestore
from scipy.spatial.transform import Rotation

from wavegrasp.recording_io.typestore import ros2_typestore

MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
STRING = "std_msgs/msg/String"
#: visualization_msgs/Marker's types used here.
ARROW, SPHERE, LINE_STRIP, TRIANGLE_LIST, TEXT = 0, 2, 4, 11, 9
NUMPY = {"uint8": np.uint8, "int8": np.int8, "uint16": np.uint16, "int16": np.int16,
         "uint32": np.uint32, "int32": np.int32, "uint64": np.uint64, "int64": np.int64,
         "float32": np.float32, "float64": np.float64}


def message(msgtype: str, store: Typestore | None = None, **fields: Any) -> Any:
    """A rosbags message of ``msgtype`` with ``fields``, every other field zero or empty."""
    store = store or ros2_typestore()
    values = {}
    for name, (kind, spec) in store.fielddefs[msgtype][1]:
        if name in fields:
            values[name] = fields[name]
        elif kind.name == "BASE":
            values[name] = {"string": "", "bool": False, "float32": 0.0,
                            "float64": 0.0}.get(spec[0], 0)
        elif kind.name == "NAME":
            values[name] = message(spec, store)
        elif kind.name == "SEQUENCE" and spec[0][0].name == "BASE":
            values[name] = np.array([], dtype=NUMPY.get(spec[0][1][0], np.uint8))
        elif kind.name == "SEQUENCE":
            values[name] = []
        else:  # a fixed-size array
            values[name] = np.zeros(spec[1], dtype=NUMPY.get(spec[0][1][0], np.float64))
    return store.types[msgtype](**values)


def cdr(msg: Any, msgtype: str) -> bytes:
    return bytes(ros2_typestore().serialize_cdr(msg, msgtype))


def stamp(ns: int) -> Any:
    return message("builtin_interfaces/msg/Time", sec=ns // 1_000_000_000,
                   nanosec=ns % 1_000_000_000)


def header(ns: int, frame_id: str) -> Any:
    return message("std_msgs/msg/Header", stamp=stamp(ns), frame_id=frame_id)


def pose(T: np.ndarray) -> Any:
    """T : array, shape (4, 4) -> geometry_msgs/Pose."""
    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
    return message("geometry_msgs/msg/Pose",
                   position=message("geometry_msgs/msg/Point", x=float(T[0, 3]),
                                    y=float(T[1, 3]), z=float(T[2, 3])),
                   orientation=message("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w))


def points(p: np.ndarray) -> list[Any]:
    """p : array, shape (n, 3) -> geometry_msgs/Point list."""
    return [message("geometry_msgs/msg/Point", x=float(a), y=float(b), z=float(c))
            for a, b, c in np.asarray(p, dtype=float).reshape(-1, 3)]


def marker(ns: str, kind: int, stamp_ns: int, frame_id: str, rgba: tuple[float, ...],
           scale: tuple[float, float, float], T: np.ndarray | None = None,
           path: np.ndarray | None = None, text: str = "") -> Any:
    """One marker: ``kind`` (ARROW, SPHERE, ...), its pose ``T`` (4, 4) in ``frame_id``,
    ``path`` (n, 3) its points (a line or triangles), ``rgba`` 0-1, ``scale`` metres."""
    return message(
        "visualization_msgs/msg/Marker", header=header(stamp_ns, frame_id), ns=ns, id=0,
        type=kind, action=0, pose=pose(np.eye(4) if T is None else T),
        scale=message("geometry_msgs/msg/Vector3", x=scale[0], y=scale[1], z=scale[2]),
        color=message("std_msgs/msg/ColorRGBA", r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3]),
        points=points(path) if path is not None else [], text=text,
        frame_locked=frame_id != "world")


def marker_array(markers: list[Any]) -> bytes:
    return cdr(message("visualization_msgs/msg/MarkerArray", markers=markers), MARKER_ARRAY)


def transforms(stamp_ns: int, frames: list[tuple[str, str, np.ndarray]]) -> bytes:
    """A TFMessage of (parent, child, T_parent_child (4, 4)) as CDR."""
    out = []
    for parent, child, T in frames:
        x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
        out.append(message(
            "geometry_msgs/msg/TransformStamped", header=header(stamp_ns, parent),
            child_frame_id=child, transform=message(
                "geometry_msgs/msg/Transform",
                translation=message("geometry_msgs/msg/Vector3", x=float(T[0, 3]),
                                    y=float(T[1, 3]), z=float(T[2, 3])),
                rotation=message("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w))))
    return cdr(message(TF_MESSAGE, transforms=out), TF_MESSAGE)


def text_message(text: str) -> bytes:
    return cdr(message(STRING, data=text), STRING)
