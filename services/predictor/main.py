"""``wavegrasp predictor [--model NAME]``: observations -> where the object will be.

Subscribes ``wavegrasp/perception/object`` (nothing else: no wave condition, no ground truth)
and publishes, for each observation with a centroid, ``wavegrasp/predictor/prediction``:
samples from now to ``horizon_periods`` wave periods ahead (at least one), each with its sigma,
and the model's parameters. ``warm`` is false until the model has measured its own errors.
"""

from __future__ import annotations

import argparse
import logging
import sys

import numpy as np
from pydantic import Field

from wavegrasp.checks import StampOrder
from wavegrasp.predictor import DEFAULT_MODEL, MODELS
from wavegrasp.predictor.forecast import Forecast
from wavegrasp.predictor.models import make_predictor
from wavegrasp.runtime.bus import Bus, Delivery
from wavegrasp.runtime.service import Service, setup_logging
from wavegrasp.runtime.settings import Settings
from wavegrasp.runtime.trace import derived_header
from wavegrasp.schemas import MotionPrediction, ObjectObservation, PredictionSample

log = logging.getLogger("wavegrasp.predictor")
PREDICTION_KEY = "wavegrasp/predictor/prediction"
#: A lead whose error cannot even be guessed yet: no planner takes it.
UNKNOWN_SIGMA_M = 1.0


class PredictorSettings(Settings):
    predictor: str = Field(DEFAULT_MODEL, description=f"one of {', '.join(MODELS)}")
    horizon_periods: float = Field(3.5, ge=1.0, description="published lead, capped at 8 s")
    guess_sigma_to_s: float = Field(4.0, description="a lead whose error has not been "
                                    "measured yet is given the largest measured sooner up to "
                                    "this lead or one period past the farthest measured, "
                                    "whichever is farther, and sigma 1 m (unknown) past it. "
                                    "Guessed to 8 s, a grasp planned 6.6 s ahead, errors "
                                    "measured to about 4 s, strayed 22 mm (random-7-004); "
                                    "unknown from the measured leads on, the first warm "
                                    "forecasts planned far less (seed 167: 64 % of "
                                    "predictions, not 90 %). The period: the forecast comes "
                                    "back to each phase once a period, and the phase the arm "
                                    "can take in time may lie just past the measured leads "
                                    "(random-173-025: 4 warm forecasts in a row planned "
                                    "nothing, each plans 4.2-4.3 s ahead with it)")


class PredictorService(Service):
    ack_after = "perception"

    def __init__(self, settings: PredictorSettings, bus: Bus | None = None) -> None:
        super().__init__(settings, bus)
        self.cfg = settings
        self.model = make_predictor(settings.predictor)
        self.epoch_ns: int | None = None
        # A repeated or older observation is refused; one far older restarts the model too.
        self.order = StampOrder(restart_s=self.model.max_gap_s)
        self.bus.subscribe("wavegrasp/perception/object", self.on_observation, ObjectObservation)

    def on_observation(self, msg: ObjectObservation, d: Delivery) -> None:
        if msg.centroid is None:
            self.counters["observations without centroid"] += 1
            return
        c = msg.centroid
        self.order.check(msg.header.stamp_ns)
        if self.epoch_ns is None:
            self.epoch_ns = msg.header.stamp_ns
        t = (msg.header.stamp_ns - self.epoch_ns) * 1e-9
        forecast = self.model.update(t, np.array([c.x, c.y, c.z]), msg.sigma_m)
        if forecast is None or not np.isfinite(forecast.period_s):
            self.counters["warming up"] += 1
            return
        self.counters["predictions"] += 1
        self.bus.publish(PREDICTION_KEY, self.message(msg, d, forecast))

    def message(self, msg: ObjectObservation, d: Delivery, f: Forecast) -> MotionPrediction:
        """The forecast as samples on the recording clock, up to ``horizon_periods``."""
        last = min(len(f.leads), int(np.ceil(self.cfg.horizon_periods * f.period_s / (
            f.leads[1] - f.leads[0]))) + 1)
        measured = np.isfinite(f.sigma)
        guess = np.full(len(f.leads), UNKNOWN_SIGMA_M)
        if measured.any():
            reach = max(self.cfg.guess_sigma_to_s, f.leads[measured].max() + f.period_s)
            guess[f.leads <= reach] = f.sigma[measured].max()
        sigma = np.where(np.isfinite(f.sigma), f.sigma, guess)
        t0_ns = self.epoch_ns + int(round(f.t0 * 1e9))
        samples = [PredictionSample(t_ns=t0_ns + int(round(lead * 1e9)), x=p[0], y=p[1], z=p[2],
                                    sigma=s)
                   for lead, p, s in zip(f.leads[:last], f.positions[:last], sigma[:last],
                                         strict=True)]
        params = {k: float(v) for k, v in f.parameters.items() if np.isfinite(v)}
        return MotionPrediction(header=derived_header(msg.header, self.name, d.recv_ns),
                                model=self.model.name, period_s=f.period_s, samples=samples,
                                parameters=params, warm=f.warm)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="wavegrasp predictor", description=__doc__)
    parser.add_argument("--model", choices=MODELS, help="default: WAVEGRASP_PREDICTOR or "
                        f"{DEFAULT_MODEL}")
    args = parser.parse_args(argv)
    try:
        settings = PredictorSettings.from_env("predictor", predictor=args.model)
        make_predictor(settings.predictor)
    except ValueError as exc:
        print(f"wavegrasp predictor: {exc}", file=sys.stderr)
        return 2
    setup_logging(settings.log_level)
    return PredictorService(settings).run()
