"""Settings from environment variables, the way compose and the launcher pass them.

Zenoh endpoints come from ``ZENOH_CONNECT`` / ``ZENOH_LISTEN`` (comma-separated, e.g.
``tcp/router:7447``) and a zenoh config file from ``ZENOH_CONFIG`` (e.g.
``keys/{service}.json5``, made by ``wavegrasp keys``); every other field ``f`` of a settings
model comes from ``WAVEGRASP_F``.
Command-line options given to a service override the environment.
"""

from __future__ import annotations

import os
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError

S = TypeVar("S", bound="Settings")

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"


def split_endpoints(text: str) -> list[str]:
    """``"tcp/a:1, tcp/b:2"`` -> ``["tcp/a:1", "tcp/b:2"]``."""
    return [part.strip() for part in text.split(",") if part.strip()]


class Settings(BaseModel):
    """What every service needs: its name, how to reach the bus, and how chatty to be."""

    model_config = ConfigDict(extra="forbid")

    service: str
    zenoh_connect: list[str] = Field(default_factory=lambda: [DEFAULT_ROUTER])
    zenoh_listen: list[str] = Field(default_factory=list)
    router_connect: list[str] = Field(
        default_factory=list, description="a router's links to other routers (the vehicle's, "
        "across the tether); a client's are zenoh_connect")
    hold_keys: list[str] = Field(
        default_factory=list, description="a router's: key expressions it never sends out "
        "through hold_interfaces (the vehicle's: the camera's full clouds stay off the "
        "tether, whoever subscribes to them topside)")
    hold_interfaces: list[str] = Field(
        default_factory=list, description="the network interfaces hold_keys stay off (the "
        "tether's)")
    zenoh_mode: Literal["client", "peer", "router"] = "client"
    zenoh_config: str | None = Field(
        None, description="zenoh JSON5 file (credentials, access control, TLS) applied under "
        "the settings above; '{service}' in it becomes the service's name")
    log_level: str = "INFO"
    clock: Literal["recording", "wall"] = Field(
        "recording", description="follow wavegrasp/clock (replays) or the wall (live vehicle)")
    stats_period_s: float = Field(1.0, gt=0)
    switch_interval_ms: float = Field(
        0.5, gt=0, description="how long the service loop may hold Python's interpreter lock "
        "while a zenoh thread waits to hand it a message (Python's default: 5 ms). Until it "
        "lets go, the waiting thread wakes at every lock release numpy makes and slows the "
        "loop: a plan computed while an acknowledgement arrived took 9.4 ms instead of 6")
    connect_timeout_s: float = Field(15.0, gt=0)
    shared_memory_mb: int = Field(
        256, ge=0, description="zenoh shared memory, MB: a process that sends large messages "
        "(camera clouds) writes each once into a pool of this size, made at its first, for "
        "subscribers on this host, the router included, to read without a copy through the "
        "network stack; a subscriber on another host gets them over the network as before. "
        "Frames stay in the pool until every receiver here has taken them: 256 MB holds 31 "
        "frames of a 672 x 376 rgb camera, a second at 30 Hz (at start-up the recorder, "
        "starved of CPU, lagged 0.6 s and filled a 64 MB pool). Only where the process may "
        "lock memory without limit (root, or ulimit -l unlimited): zenoh locks its pools, and "
        "under a limit it stalled or refused them. 0: off")
    health_file: Path | None = Field(
        None, description="touched every second while the service runs and reaches the "
        "router (compose's healthcheck reads its age)")

    @classmethod
    def from_env(
        cls: type[S], service: str, env: Mapping[str, str] | None = None, **overrides: Any
    ) -> S:
        """Build settings from ``env`` (default ``os.environ``); ``overrides`` win.

        Raises
        ------
        ValueError
            naming the environment variable whose value is invalid.
        """
        env = os.environ if env is None else env
        values: dict[str, Any] = {"service": service}
        for name in cls.model_fields:
            var = name.upper() if name.startswith("zenoh_") else f"WAVEGRASP_{name.upper()}"
            if var in env and name != "service":
                text = env[var]
                is_list = typing.get_origin(cls.model_fields[name].annotation) is list
                values[name] = split_endpoints(text) if is_list else text
        values.update({k: v for k, v in overrides.items() if v is not None})
        try:
            return cls(**values)
        except ValidationError as exc:
            first = exc.errors()[0]
            field = str(first["loc"][0]) if first["loc"] else "?"
            var = field.upper() if field.startswith("zenoh_") else f"WAVEGRASP_{field.upper()}"
            raise ValueError(f"setting {field} (env {var}): {first['msg']}") from None


class ArmTopics(BaseModel):
    """Where the arm is commanded and reports, as ros2_control's controllers name their
    topics (zenoh-bridge-ros2dds maps ``/a/b`` to the key ``a/b``): the commander (the gate)
    sends, the arm (the sim, or a real one behind a bridge) follows and reports, the planner
    reads both."""

    arm_urdf: str | None = Field(None, description="the arm's URDF (default: wavegrasp's "
                                 "Bravo-7-like model)")
    arm_trajectory_key: str = Field(
        "arm/joint_trajectory_controller/joint_trajectory", description="the arm's "
        "trajectory_msgs/msg/JointTrajectory: approved plans, updates, aborts and standby "
        "moves, each replacing what was commanded from its first point on")
    jaw_trajectory_key: str = Field(
        "jaw/joint_trajectory_controller/joint_trajectory", description="the jaw's finger "
        "joints' trajectory_msgs/msg/JointTrajectory: open, narrowed for the final move, "
        "closed, opened again")
    joint_states_key: str = Field("joint_states", description="the arm's and fingers' "
                                  "sensor_msgs/msg/JointState (ros2_control's joint state "
                                  "broadcaster's topic)")
