"""Perception accuracy and speed: ``python -m wavegrasp.ops.bench_perception [--seconds 20]``.

Runs the perception pipeline (offline, frame by frame, as the service does) over wave-tank
recordings of all 12 wave × object configurations and over objects and camera poses the
pipeline was not tuned on (another sphere size, a larger bottle, the camera moved by tens of
centimetres), and over boxes, ellipsoids and bottles with a neck (``FAMILIES``), and prints
per recording: frames with an observation, centroid RMSE and mean bias against ground truth
(the volume centroid), points per frame, and per-frame time (median, p99). The camera is set
to 288 × 216 pixels, about 30 000 points a frame. Recordings are generated into the cache on
first use.
"""

from __future__ import annotations

import argparse
import re

import numpy as np

from wavegrasp.ops.sample import cached_recording
from wavegrasp.perception.evaluate import HEADER, evaluate
from wavegrasp.wavetank.body import OBJECTS
from wavegrasp.wavetank.scenario import CameraSpec, ObjectModel, Scenario, paper_scenario
from wavegrasp.wavetank.waves import TABLE_I

CAMERA_30K = {"width": 288, "height": 216}
UNSEEN = [  # (label, RecordConfig overrides)
    ("smaller sphere (buoy x0.7)", {"wave": 1, "object": "buoy", "object_scale": 0.7}),
    ("larger sphere (buoy x1.4)", {"wave": 2, "object": "buoy", "object_scale": 1.4}),
    ("larger bottle (x1.5)", {"wave": 3, "object": "bottle", "object_scale": 1.5}),
    ("camera 30 cm right", {"wave": 1, "object": "can_empty", "camera_offset": (0.3, 0.0, 0.0)}),
    ("camera 25 cm nearer, 15 cm up",
     {"wave": 2, "object": "can_half", "camera_offset": (0.0, 0.25, 0.15)}),
    ("camera 25 cm left, 20 cm back, 10 cm up",
     {"wave": 1, "object": "bottle", "camera_offset": (-0.25, -0.2, 0.1)}),
]

#: Shapes no sphere or cylinder fits (label, wave, object). The first five were looked at
#: while the box and solid-of-revolution fits were written; the rest were not.
FAMILIES = [
    ("box 8 x 5 x 15 cm, turned 30 deg", 2, {"family": "box", "diameter_m": 0.08,
                                            "depth_m": 0.05, "length_m": 0.15,
                                            "mass_kg": 0.25, "turn_deg": 30}),
    ("cube 7 cm, turned -50 deg", 2, {"family": "box", "diameter_m": 0.07, "depth_m": 0.07,
                                      "length_m": 0.07, "mass_kg": 0.15, "turn_deg": -50}),
    ("ellipsoid 7 x 14 cm", 2, {"family": "ellipsoid", "diameter_m": 0.07, "length_m": 0.14,
                                "mass_kg": 0.15}),
    ("ellipsoid 12 x 8 cm (flat)", 2, {"family": "ellipsoid", "diameter_m": 0.12,
                                       "length_m": 0.08, "mass_kg": 0.25}),
    ("bottle 6.5 x 20 cm, neck down", 2, {"family": "bottle", "diameter_m": 0.065,
                                          "length_m": 0.2, "neck_diameter_m": 0.027,
                                          "neck_length_m": 0.04, "mass_kg": 0.12}),
    ("box 10 x 6 x 20 cm, turned 55 deg", 3, {"family": "box", "diameter_m": 0.1,
                                             "depth_m": 0.06, "length_m": 0.2,
                                             "mass_kg": 0.5, "turn_deg": 55}),
    ("box 6 x 4 x 10 cm, turned -20 deg", 1, {"family": "box", "diameter_m": 0.06,
                                             "depth_m": 0.04, "length_m": 0.1,
                                             "mass_kg": 0.1, "turn_deg": -20}),
    ("ellipsoid 9 x 12 cm", 1, {"family": "ellipsoid", "diameter_m": 0.09, "length_m": 0.12,
                                "mass_kg": 0.2}),
    ("bottle 8 x 24 cm, neck down", 3, {"family": "bottle", "diameter_m": 0.08,
                                        "length_m": 0.24, "neck_diameter_m": 0.032,
                                        "neck_length_m": 0.05, "mass_kg": 0.3}),
    ("bottle 5 x 16 cm, neck up", 1, {"family": "bottle", "diameter_m": 0.05,
                                      "length_m": 0.16, "neck_diameter_m": 0.022,
                                      "neck_length_m": 0.03, "neck": "up", "mass_kg": 0.08}),
    ("box 8 x 5 x 15 cm, face-on", 2, {"family": "box", "diameter_m": 0.08, "depth_m": 0.05,
                                      "length_m": 0.15, "mass_kg": 0.25}),
]


def family_scenario(label: str, wave: int, obj: dict, seconds: float, seed: int) -> Scenario:
    """The paper's tank (Table I's ``wave``) with another object and the 30 k-point camera."""
    slug = re.sub(r"[^a-z0-9.]+", "-", label.lower()).strip("-")
    return paper_scenario(wave, "buoy", name=f"family-w{wave}-{slug}",
                          object=ObjectModel(name=label.split(" ")[0], **obj),
                          seconds=seconds, seed=seed, camera=CameraSpec(**CAMERA_30K))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--seed", type=int, default=1)
    a = p.parse_args(argv)
    runs = [(f"wave {w}, {o}", {"wave": w, "object": o}) for w in TABLE_I for o in OBJECTS]
    runs += [(label, cfg) for label, cfg in UNSEEN]
    runs += [(label, {"scenario": family_scenario(label, wave, obj, a.seconds, a.seed)})
             for label, wave, obj in FAMILIES]
    print(HEADER.replace("| recording |", "| configuration |"))
    times, worst_rmse, worst_bias, worst_seen = [], 0.0, 0.0, 1.0
    for label, cfg in runs:
        path = cached_recording(cfg["scenario"]) if "scenario" in cfg else cached_recording(
            seconds=a.seconds, seed=a.seed, camera=CAMERA_30K, **cfg)
        ev = evaluate(path)
        print(ev.row().replace(f"| {path.name} |", f"| {label} |"), flush=True)
        times.append(ev.times_ms)
        if len(ev.errors):
            worst_rmse = max(worst_rmse, ev.rmse)
            worst_bias = max(worst_bias, float(np.linalg.norm(ev.bias)))
        worst_seen = min(worst_seen, ev.observed)
    all_times = np.concatenate(times)
    print(f"\nall {len(all_times)} frames: median {np.median(all_times):.2f} ms, "
          f"p99 {np.percentile(all_times, 99):.2f} ms; worst RMSE {worst_rmse * 1e3:.2f} mm, "
          f"worst mean bias {worst_bias * 1e3:.2f} mm, fewest observed {worst_seen:.1%}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
