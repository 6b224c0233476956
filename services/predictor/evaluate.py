"""Predictor models against ground truth, fed the perception service's centroids.

For every warm forecast (the ones the pipeline acts on) made after ``warmup_s``, the predicted
position at 0.25, 0.5 and 1 wave period ahead (the wave's own period, known to the benchmark,
never to the models) is compared with the ground truth there; coverage is the share of
1-period errors within 2 sigma.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from wavegrasp.perception.evaluate import Track
from wavegrasp.predictor.models import make_predictor

FRACTIONS = (0.25, 0.5, 1.0)


@dataclass
class PredictorScore:
    """rmse : metres at each of FRACTIONS of the period; coverage : share within 2 sigma at 1T;
    update_ms : per update; forecasts : how many were scored."""

    model: str
    rmse: tuple[float, ...]
    coverage: float
    update_ms: np.ndarray
    forecasts: int


def score(track: Track, model: str, period_s: float, warmup_s: float = 10.0) -> PredictorScore:
    predictor = make_predictor(model)
    t_truth = (track.truth_ns - track.stamps_ns[0]) * 1e-9
    errors: list[list[float]] = [[] for _ in FRACTIONS]
    inside, times = [], []
    for stamp, centre, sigma in zip(track.stamps_ns, track.centres, track.sigmas, strict=True):
        if np.isnan(centre[0]):
            continue
        t = (stamp - track.stamps_ns[0]) * 1e-9
        start = time.perf_counter()
        forecast = predictor.update(t, centre, sigma)
        times.append((time.perf_counter() - start) * 1e3)
        if (forecast is None or not forecast.warm or t < warmup_s
                or forecast.t0 + period_s > t_truth[-1]):
            continue
        for i, frac in enumerate(FRACTIONS):
            target = forecast.t0 + frac * period_s
            true = np.array([np.interp(target, t_truth, track.truth[:, k]) for k in range(3)])
            err = float(np.linalg.norm(forecast.at(target) - true))
            errors[i].append(err)
        inside.append(errors[-1][-1] <= 2 * np.interp(period_s, forecast.leads, forecast.sigma))
    rmse = tuple(float(np.sqrt(np.mean(np.square(e)))) if e else float("nan") for e in errors)
    return PredictorScore(model, rmse, float(np.mean(inside)) if inside else float("nan"),
                          np.asarray(times), len(errors[-1]))
