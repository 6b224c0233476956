"""Measurements on a recording's ground truth: dominant period, amplitudes, speeds."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from wavegrasp.recording_io.reader import open_recording
from wavegrasp.recording_io.typestore import ros2_typestore


def read_groundtruth(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Ground truth of a recording: times (n,) seconds from the first sample, and centroids
    (n, 3) metres in world."""
    store = ros2_typestore()
    t, p = [], []
    for m in open_recording(path, topics=("/groundtruth/object",)).messages():
        pose = store.deserialize_cdr(m.cdr, m.msgtype).pose.position
        t.append(m.log_time_ns)
        p.append((pose.x, pose.y, pose.z))
    if len(t) < 2:
        raise ValueError(f"{path}: fewer than two ground-truth poses")
    times = (np.asarray(t) - t[0]) * 1e-9
    return times, np.asarray(p)


def dominant_period(times: np.ndarray, positions: np.ndarray) -> float:
    """Period (s) of the strongest peak in the horizontal velocity spectrum.

    times : array, shape (n,), seconds, evenly spaced; positions : array, shape (n, 3), metres.
    Velocity rather than position, so slow sway and drift do not mask the wave's period; the
    peak is refined by zero padding and a parabola through the three highest bins.
    """
    dt = float(np.median(np.diff(times)))
    v = np.diff(positions[:, :2], axis=0) / dt
    v -= v.mean(axis=0)
    n = 16 * len(v)
    power = sum(np.abs(np.fft.rfft(v[:, i] * np.hanning(len(v)), n)) ** 2 for i in range(2))
    k = int(np.argmax(power[1:-1])) + 1
    a, b, c = np.log(power[k - 1 : k + 2])
    shift = 0.5 * (a - c) / (a - 2 * b + c)
    return 1.0 / ((k + shift) / (n * dt))


def motion_summary(times: np.ndarray, positions: np.ndarray) -> dict[str, float]:
    """Half peak-to-peak amplitude per axis (m) and the highest speed (m/s)."""
    dt = float(np.median(np.diff(times)))
    half = (positions.max(axis=0) - positions.min(axis=0)) / 2
    speed = np.linalg.norm(np.diff(positions, axis=0), axis=1) / dt
    return {"amp_x": half[0], "amp_y": half[1], "amp_z": half[2], "max_speed": float(speed.max())}
