"""A stand-in arm written against the ROS 2 message types alone (zenoh, rosbags and numpy; no
wavegrasp code): what a ros2_control arm behind zenoh-bridge-ros2dds is to wavegrasp.

It follows the ``trajectory_msgs/msg/JointTrajectory`` sent to its arm's and its jaw's joint
trajectory controllers exactly (a new one replaces the rest of the one followed from its first
point on, as the controller does), on the time of ``rosgraph_msgs/msg/Clock`` on ``clock`` (a
node with use_sim_time), and sends ``sensor_msgs/msg/JointState`` on ``joint_states`` at each
tick of it, with no encoding named, as the bridge sends them. Stops on SIGTERM or SIGINT.

    python tests/standin_arm.py --joints j1,...,j6 --home 0,...,0 --fingers f1,f2 --open 0.05

``ZENOH_CONNECT`` names the router (default tcp/127.0.0.1:7447).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import threading

import numpy as np
import zenoh
from rosbags.typesys import Stores, get_typestore

TYPES = get_typestore(Stores.ROS2_HUMBLE)
ARM_KEY = "arm/joint_trajectory_controller/joint_trajectory"
JAW_KEY = "jaw/joint_trajectory_controller/joint_trajectory"


def seconds(t) -> float:
    return t.sec + t.nanosec * 1e-9


class Joints:
    """Named joints following trajectories exactly: times (k,) s, positions (k, n)."""

    def __init__(self, names: list[str], start: list[float]) -> None:
        self.names = names
        self.times, self.q = np.array([0.0]), np.array([start], dtype=float)
        self.taken = 0

    def take(self, msg) -> None:
        if sorted(msg.joint_names) != sorted(self.names) or not len(msg.points):
            return  # another controller's, or a stop: not this stand-in's business
        order = [list(msg.joint_names).index(n) for n in self.names]
        start = seconds(msg.header.stamp)
        times = np.array([start + seconds(p.time_from_start) for p in msg.points])
        q = np.array([np.asarray(p.positions)[order] for p in msg.points])
        keep = self.times < times[0]
        self.times, self.q = np.concatenate([self.times[keep], times]), np.vstack([self.q[keep], q])
        self.taken += 1

    def at(self, t: float, dt: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
        def q(x: float) -> np.ndarray:
            return np.array([np.interp(x, self.times, column) for column in self.q.T])
        return q(t), (q(t + dt) - q(t - dt)) / (2 * dt)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--joints", required=True)
    p.add_argument("--home", required=True)
    p.add_argument("--fingers", required=True)
    p.add_argument("--open", type=float, required=True, help="each finger's open position, m")
    a = p.parse_args()
    names, fingers = a.joints.split(","), a.fingers.split(",")
    arm = Joints(names, [float(x) for x in a.home.split(",")])
    jaw = Joints(fingers, [a.open] * len(fingers))
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    endpoints = os.environ.get("ZENOH_CONNECT", "tcp/127.0.0.1:7447").split(",")
    conf.insert_json5("connect/endpoints", json.dumps(endpoints))
    conf.insert_json5("scouting/multicast/enabled", "false")
    lock, stop = threading.Lock(), threading.Event()
    with zenoh.open(conf) as session:
        state = session.declare_publisher("joint_states")

        def on_trajectory(sample: zenoh.Sample) -> None:
            msg = TYPES.deserialize_cdr(sample.payload.to_bytes(),
                                        "trajectory_msgs/msg/JointTrajectory")
            with lock:
                (arm if str(sample.key_expr) == ARM_KEY else jaw).take(msg)

        def on_clock(sample: zenoh.Sample) -> None:
            now = TYPES.deserialize_cdr(sample.payload.to_bytes(), "rosgraph_msgs/msg/Clock").clock
            with lock:
                (q, qd), (f, fd) = arm.at(seconds(now)), jaw.at(seconds(now))
            msg = TYPES.types["sensor_msgs/msg/JointState"](
                header=TYPES.types["std_msgs/msg/Header"](stamp=now, frame_id=""),
                name=names + fingers, position=np.concatenate([q, f]),
                velocity=np.concatenate([qd, fd]), effort=np.zeros(0))
            state.put(bytes(TYPES.serialize_cdr(msg, "sensor_msgs/msg/JointState")))

        subs = [session.declare_subscriber(ARM_KEY, on_trajectory),
                session.declare_subscriber(JAW_KEY, on_trajectory),
                session.declare_subscriber("clock", on_clock)]
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
        print(f"stand-in arm: following {ARM_KEY} and {JAW_KEY}", flush=True)
        stop.wait()
        print(f"stand-in arm: took {arm.taken} arm and {jaw.taken} jaw trajectories", flush=True)
        for sub in subs:
            sub.undeclare()


if __name__ == "__main__":
    main()
