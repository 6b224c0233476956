"""Our own messages in a run's MCAP file, as their pydantic models.

A run records them as ROS 2 channels (topic ``/wavegrasp/...``, CDR, ``ros2msg`` schema of
their ``wavegrasp_msgs`` type); runs recorded before that, and JSON a tool published, as JSON
channels (topic ``wavegrasp/...``, ``jsonschema``). Both read the same here.
"""

from __future__ import annotations

from collections.abc import Collection, Iterator
from pathlib import Path

from mcap.records import Channel, Message, Schema
from pydantic import BaseModel

from wavegrasp.recording_io.mcap_read import read_mcap
from wavegrasp.schemas import MESSAGE_TYPES
from wavegrasp.schemas.ros import PACKAGE, from_cdr


def own_topics(keys: Collection[str]) -> list[str]:
    """The MCAP topics ``keys`` (``wavegrasp/...``) may be recorded on: CDR and JSON."""
    return [t for key in keys for t in ("/" + key.lstrip("/"), key.lstrip("/"))]


def decode_own(schema: Schema | None, channel: Channel, message: Message) -> BaseModel | None:
    """The model of one of our messages, or None for any other channel's; ValueError (or
    pydantic's ValidationError) naming the topic when its bytes are not a valid message."""
    if schema is None:
        return None
    name = schema.name.rpartition("/")[2]
    model = MESSAGE_TYPES.get(name)
    if model is None:
        return None
    if channel.message_encoding == "cdr" and schema.name == f"{PACKAGE}/msg/{name}":
        try:
            return from_cdr(message.data, model)
        except ValueError as exc:
            raise ValueError(f"{channel.topic}: {exc}") from None
    if channel.message_encoding == "json":
        return model.model_validate_json(message.data)
    return None


def read_own(path: str | Path, keys: Collection[str]) -> Iterator[tuple[str, BaseModel, int]]:
    """(key, message, log time ns) of our messages on ``keys`` in MCAP file ``path``, in
    log-time order (:func:`~wavegrasp.recording_io.mcap_read.read_mcap`'s errors)."""
    for schema, channel, message in read_mcap(path, own_topics(keys)):
        msg = decode_own(schema, channel, message)
        if msg is not None:
            yield channel.topic.lstrip("/"), msg, message.log_time
