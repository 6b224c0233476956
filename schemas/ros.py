"""Every message of ours as a ROS 2 interface type (package ``wavegrasp_msgs``) and as CDR.

The pydantic models are the one source: :func:`definitions` derives each ``.msg`` from its
model (``schemas/msg/NAME.msg`` holds them for colcon; ``python -m wavegrasp.schemas.export``
writes them, and a test fails while they differ), and :func:`to_cdr` / :func:`from_cdr`
convert between a model and its CDR bytes (by :mod:`wavegrasp.schemas.cdr`, compiled per
model; tested against rosbags' serializer of the same definitions). Mapping, field by field:

- ``header`` (:class:`Header`) -> ``std_msgs/Header header`` (its ``stamp`` from ``stamp_ns``,
  ``frame_id``) and ``wavegrasp_msgs/Trace trace`` (``seq`` and the ``hops``): ROS tools find
  the stamp and frame where they look for them.
- :class:`Vec3` -> ``geometry_msgs/Point``, :class:`Quaternion` and :class:`Pose` -> their
  ``geometry_msgs`` namesakes; other nested models -> ``wavegrasp_msgs/<Model>``.
- ``int`` -> ``int64``, ``float`` -> ``float64``, ``bool``, ``str`` and ``Literal`` -> ``string``;
  ``list[X]`` -> ``X[]``; an optional ``X | None`` -> ``X[<=1]`` (empty: None).
- ``dict[str, float]`` -> ``FloatEntry[]``, ``dict[str, int]`` -> ``CountEntry[]``,
  ``dict[str, str]`` -> ``diagnostic_msgs/KeyValue[]``, ``dict[str, float | str | bool]`` ->
  ``ValueEntry[]``: key and value, in the dict's order.

Fields a sender adds beyond its model (``extra="allow"``) do not travel in CDR.
"""

from __future__ import annotations

import inspect
import typing
from functools import cache
from typing import Any, Literal

from pydantic import BaseModel
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from wavegrasp.schemas import MESSAGE_TYPES, ROS_KEYS, Header, Hop, Pose, Quaternion, Vec3
from wavegrasp.schemas.cdr import _entry, _item, _optional, _plain, compile_all, decode, encode

PACKAGE = "wavegrasp_msgs"
#: Models that are ROS 2 standard types, field for field.
STANDARD = {Vec3: "geometry_msgs/msg/Point", Quaternion: "geometry_msgs/msg/Quaternion",
            Pose: "geometry_msgs/msg/Pose"}
#: The entries a dict travels as, by its value type.
ENTRY_TEXT = {
    "FloatEntry": "string key\nfloat64 value\n",
    "CountEntry": "string key\nint64 value\n",
    "ValueEntry": "# A value that is a number, a text or a flag: kind says which field holds it.\n"
                  "uint8 NUMBER=0\nuint8 TEXT=1\nuint8 FLAG=2\n"
                  "string key\nuint8 kind\nfloat64 number\nstring text\nbool flag\n",
    "Trace": "# The message's sequence number and every service it went through.\n"
             "int64 seq\nHop[] hops\n",
}
def msgtype(name: str) -> str:
    """``wavegrasp_msgs/msg/<name>``: the ROS 2 type of model or entry ``name``."""
    return f"{PACKAGE}/msg/{name}"


def _ros_type(annotation: Any) -> str:
    """The .msg type (without array suffix) of a scalar or model annotation."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return STANDARD.get(annotation, annotation.__name__).replace("/msg/", "/")
    if typing.get_origin(annotation) is Literal or annotation is str:
        return "string"
    return {int: "int64", float: "float64", bool: "bool"}[annotation]


def _field_line(name: str, annotation: Any) -> str:
    inner = _optional(annotation)
    if inner is not None:
        return f"{_ros_type(inner)}[<=1] {name}"
    origin = typing.get_origin(annotation)
    if origin is list:
        return f"{_ros_type(_item(annotation, 0))}[] {name}"
    if origin is dict:
        return f"{_entry(_item(annotation, 1))}[] {name}"
    return f"{_ros_type(_plain(annotation))} {name}"


def msg_text(model: type[BaseModel]) -> str:
    """The ``.msg`` definition of ``model``, its field descriptions as comments."""
    lines = [f"# {line}".rstrip() for line in inspect.cleandoc(model.__doc__ or "").splitlines()]
    for name, field in model.model_fields.items():
        if field.annotation is Header:
            lines += ["std_msgs/Header header", "Trace trace"]
            continue
        if field.description:
            lines.append(f"# {field.description}")
        lines.append(_field_line(name, field.annotation))
    return "\n".join(lines) + "\n"


def _nested(model: type[BaseModel], seen: dict[str, type[BaseModel]]) -> None:
    for field in model.model_fields.values():
        for arg in (field.annotation, *typing.get_args(field.annotation)):
            for inner in (arg, *typing.get_args(arg)):
                if (isinstance(inner, type) and issubclass(inner, BaseModel)
                        and inner not in STANDARD and inner is not Header
                        and inner.__name__ not in seen):
                    seen[inner.__name__] = inner
                    _nested(inner, seen)


@cache
def definitions() -> dict[str, str]:
    """``.msg`` text of every ``wavegrasp_msgs`` type, by name (``ObjectObservation``...)."""
    models: dict[str, type[BaseModel]] = dict(MESSAGE_TYPES)
    for model in list(models.values()):
        _nested(model, models)
    out = {name: msg_text(model) for name, model in sorted(models.items())}
    out["Hop"] = msg_text(Hop)
    out.update(ENTRY_TEXT)
    return dict(sorted(out.items()))


@cache
def typestore() -> Typestore:
    """ROS 2 Humble's types with ``wavegrasp_msgs``'s registered."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    found: dict = {}
    for name, text in definitions().items():
        found.update(get_types_from_msg(text, msgtype(name)))
    store.register(found)
    return store


#: The ROS 2 types on our keys that are written and read by hand, not by rosbags
#: (``recording_io/joint_cdr.py``).
BY_HAND = {"sensor_msgs/msg/JointState", "trajectory_msgs/msg/JointTrajectory"}


def warm_up() -> None:
    """Generate rosbags' CDR code of the ROS 2 types a service reads with it, and compile our
    own messages' codecs, now, not at its first message: the first message of each type took
    3-13 ms more (a plan 11 ms), on the camera-to-decision path. (Generating rosbags' code
    for every type of ours too, which it no longer reads, took some 0.4 s a run.)"""
    store = typestore()
    for name in set(ROS_KEYS.values()) - BY_HAND:  # ours are by hand too (schemas/cdr.py)
        store.get_msgdef(name)
    compile_all()


# -- the codec -------------------------------------------------------------------------------
def to_cdr(msg: BaseModel) -> bytes:
    """``msg`` as little-endian CDR of its ``wavegrasp_msgs`` type (with the 4-byte header),
    written by :mod:`wavegrasp.schemas.cdr` (rosbags' bytes, several times sooner)."""
    return encode(msg)


def from_cdr(data: bytes | memoryview, model: type[BaseModel]) -> BaseModel:
    """``model`` from CDR ``data``; ValueError (or pydantic's ValidationError) naming what is
    wrong when the bytes are not a valid message of its type."""
    try:
        fields = decode(data, model)
    except ValueError as exc:
        raise ValueError(f"not a valid {msgtype(model.__name__)}: {exc}") from None
    return model.__pydantic_validator__.validate_python(fields)  # model_validate, 1 us sooner
