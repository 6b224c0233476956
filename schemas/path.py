"""How a prediction is read between its samples: a cubic spline through them.

A :class:`~wavegrasp.schemas.MotionPrediction` samples a smooth motion every ``dt`` (0.1 s).
Read linearly between samples, a 0.1 m swing of period 1.25 s is off by up to 3 mm halfway
between two (A ω² dt² / 8), more than the predictor's own error; a cubic spline through the
samples (not-a-knot) is off by a hundredth of that. Every reader (planner, gate, sim,
benchmarks) reads a prediction with :func:`path_at`; before the first sample and after the
last it holds the end value, as ``numpy.interp`` does.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline


def path_spline(times: np.ndarray, positions: np.ndarray) -> CubicSpline:
    """times : array, shape (n,), strictly increasing (any unit); positions : array, shape
    (n, 3). A spline through them; linear for two samples."""
    times, positions = np.asarray(times, dtype=float), np.asarray(positions, dtype=float)
    if len(times) < 2:
        raise ValueError(f"a path needs at least 2 samples, got {len(times)}")
    return CubicSpline(times, positions, bc_type="not-a-knot" if len(times) > 2 else "natural")


def path_at(spline: CubicSpline, t: float | np.ndarray, derivative: int = 0) -> np.ndarray:
    """Position (or its ``derivative``) at ``t``, held at the ends: shape (3,) for a scalar
    ``t``, else (k, 3). A derivative is zero outside the samples."""
    lo, hi = spline.x[0], spline.x[-1]
    ts = np.atleast_1d(np.asarray(t, dtype=float))
    out = spline(np.clip(ts, lo, hi), derivative)
    if derivative:
        out[(ts < lo) | (ts > hi)] = 0.0
    return out[0] if np.ndim(t) == 0 else out


def interpolate_path(times: np.ndarray, positions: np.ndarray,
                     t: float | np.ndarray) -> np.ndarray:
    """:func:`path_at` of a spline through ``times`` (n,) and ``positions`` (n, 3) at ``t``."""
    return path_at(path_spline(times, positions), t)
