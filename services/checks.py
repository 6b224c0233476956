"""Input checks shared by the packages; each raises ValueError naming the problem."""

from __future__ import annotations

import numpy as np


def check_vector(name: str, v: np.ndarray, n: int) -> np.ndarray:
    """Return `v` as a finite float array, shape (n,)."""
    v = np.asarray(v, dtype=float)
    if v.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be finite, got {v}")
    return v


def check_unit(name: str, v: np.ndarray) -> np.ndarray:
    """Return `v` (shape (3,)) normalised; raise ValueError if it is far from unit length."""
    v = check_vector(name, v, 3)
    norm = float(np.linalg.norm(v))
    if abs(norm - 1.0) > 1e-3:
        raise ValueError(f"{name} must be a unit vector, has length {norm:.6g}")
    return v / norm


_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])
_EYE3 = np.eye(3)


def check_transform(name: str, T: np.ndarray) -> np.ndarray:
    """Return `T` as a float array, shape (4, 4); raise ValueError unless it is rigid."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"{name} must have shape (4, 4), got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{name} must be finite")
    # Max-abs tests rather than np.allclose: the planner checks every IK target (~80 µs less).
    if np.abs(T[3] - _LAST_ROW).max() > 1e-8:
        raise ValueError(f"{name} must have last row (0, 0, 0, 1), got {T[3]}")
    R = T[:3, :3]
    if not (np.abs(R @ R.T - _EYE3).max() <= 1e-6 and np.linalg.det(R) > 0):
        raise ValueError(f"{name} rotation part is not a proper rotation matrix")
    return T


def check_positive(name: str, value: float) -> float:
    """Return `value` as a float; raise ValueError unless it is finite and > 0."""
    value = float(value)
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return value


def check_fraction(name: str, value: float) -> None:
    """Raise ValueError unless 0 <= `value` < 1."""
    if not 0.0 <= value < 1.0:
        raise ValueError(f"{name} must be in [0, 1), got {value!r}")


class StampOrder:
    """The newest stamp of a stream, to refuse messages that repeat it or come from before it.

    A stamp more than ``restart_s`` older than the newest starts the stream over (a replay
    begun again, a clock reset): it is taken and becomes the newest.
    """

    def __init__(self, restart_s: float) -> None:
        self.restart_ns = round(restart_s * 1e9)
        self.last_ns: int | None = None

    def check(self, stamp_ns: int) -> None:
        """Take ``stamp_ns``; ValueError if it is a duplicate or out of order."""
        last = self.last_ns
        if last is not None and last - self.restart_ns < stamp_ns:
            check_after(stamp_ns, last)
        self.last_ns = stamp_ns


def check_after(stamp_ns: int, last_ns: int | None) -> None:
    """Raise ValueError if ``stamp_ns`` repeats ``last_ns`` or comes before it."""
    if last_ns is not None and stamp_ns <= last_ns:
        kind = "duplicate" if stamp_ns == last_ns else "out of order"
        raise ValueError(f"{kind}: stamp {stamp_ns} <= last {last_ns}")
