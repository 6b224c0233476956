"""Perception against ground truth: ``python -m wavegrasp.perception.evaluate REC [REC ...]``.

Runs the pipeline over every camera frame of each recording, offline (no bus), read as the
service reads them (an organized cloud in windows, thinned: ``--whole``,
``--window-max-points``), and compares
each centroid with the ground truth at the frame's stamp (the generator writes both at the same
instant). Prints per recording: frames observed, centroid RMSE and mean bias (per axis), and
per-frame processing time (median, p99).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from wavegrasp.perception.fit import ShapeFit
from wavegrasp.perception.pipeline import Perception, PerceptionConfig
from wavegrasp.perception.window import WindowReader
from wavegrasp.recording_io.reader import open_recording
from wavegrasp.recording_io.ros_msgs import StaticTransforms, decode_pose, decode_tf, view_points


@dataclass
class Evaluation:
    """errors : array, shape (m, 3), metres, world (estimate − truth) for observed frames."""

    path: Path
    frames: int
    errors: np.ndarray
    times_ms: np.ndarray
    points: np.ndarray

    @property
    def observed(self) -> float:
        return len(self.errors) / max(self.frames, 1)

    @property
    def rmse(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.errors**2, axis=1))))

    @property
    def bias(self) -> np.ndarray:
        return self.errors.mean(axis=0)

    def row(self) -> str:
        b = self.bias * 1e3
        return (f"| {self.path.name} | {self.observed:.1%} | {self.rmse * 1e3:.2f} | "
                f"{b[0]:+.2f}, {b[1]:+.2f}, {b[2]:+.2f} ({np.linalg.norm(b):.2f}) | "
                f"{np.median(self.points):.0f} | {np.median(self.times_ms):.2f} | "
                f"{np.percentile(self.times_ms, 99):.2f} |")


HEADER = ("| recording | observed | RMSE (mm) | mean bias x, y, z (norm) (mm) | points/frame "
          "| median (ms) | p99 (ms) |\n|---|---|---|---|---|---|---|")


@dataclass
class Track:
    """What perception saw in a recording, beside the truth.

    stamps_ns : array, shape (n,), camera frames; centres : array, shape (n, 3), metres, world,
    NaN where no centroid was reported; sigmas : shape (n,), metres, the reported uncertainty;
    times_ms, points : per frame; truth_ns, truth : the ground truth, shape (m,) and (m, 3);
    last_fit : the last frame's shape fit (None if none was fitted); last_span : its
    :attr:`~wavegrasp.perception.pipeline.FrameResult.span`.
    """

    path: Path
    stamps_ns: np.ndarray
    centres: np.ndarray
    sigmas: np.ndarray
    times_ms: np.ndarray
    points: np.ndarray
    truth_ns: np.ndarray
    truth: np.ndarray
    last_fit: ShapeFit | None = None
    last_span: tuple[float, float] | None = None


def run_perception(path: Path, cfg: PerceptionConfig | None = None,
                   reader: WindowReader | None = None) -> Track:
    """Run the pipeline over every camera frame of ``path`` read as the service reads them
    (``reader``, default :class:`WindowReader`'s), timing each frame."""
    perception = Perception(cfg)
    reader = reader or WindowReader()
    tf = StaticTransforms()
    truth: dict[int, np.ndarray] = {}
    stamps, centres, sigmas, times, sizes = [], [], [], [], []
    last_fit, last_span = None, None
    for m in open_recording(path).messages():
        if m.topic == "/tf_static":
            tf.update(decode_tf(m.cdr))
        elif m.topic == "/groundtruth/object":
            T, _, stamp = decode_pose(m.cdr)
            truth[stamp] = T[:3, 3]
        else:
            start = time.perf_counter()
            view = view_points(m.cdr)
            T = tf.lookup("world", view.frame_id)
            region = perception.search_region(view.stamp_ns) if view.organized else None
            cloud, _ = reader.read(view, region, T)
            result = perception.process(cloud.points, T, cloud.stamp_ns)
            times.append((time.perf_counter() - start) * 1e3)
            sizes.append(len(cloud.points))
            stamps.append(cloud.stamp_ns)
            centres.append(np.full(3, np.nan) if result.fit is None else result.fit.centre)
            sigmas.append(np.nan if result.fit is None else result.fit.sigma)
            if result.fit is not None:
                last_fit, last_span = result.fit, result.span
    truth_ns = np.array(sorted(truth))
    return Track(Path(path), np.array(stamps), np.reshape(centres, (-1, 3)), np.array(sigmas),
                 np.array(times),
                 np.array(sizes), truth_ns, np.array([truth[k] for k in truth_ns]), last_fit,
                 last_span)


def evaluate(path: Path, cfg: PerceptionConfig | None = None,
             reader: WindowReader | None = None) -> Evaluation:
    """Centroid errors against the ground truth at each frame's stamp."""
    track = run_perception(path, cfg, reader)
    truth = dict(zip(track.truth_ns.tolist(), track.truth, strict=True))
    seen = ~np.isnan(track.centres[:, 0])
    errors = [c - truth[s] for s, c in zip(track.stamps_ns[seen].tolist(), track.centres[seen],
                                           strict=True) if s in truth]
    return Evaluation(Path(path), len(track.stamps_ns), np.reshape(errors, (-1, 3)),
                      track.times_ms, track.points)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recordings", nargs="+", type=Path)
    p.add_argument("--whole", action="store_true", help="read organized clouds whole, not "
                   "in windows as the service does")
    p.add_argument("--window-max-points", type=int, default=10_000,
                   help="an organized window's points at most (WAVEGRASP_WINDOW_MAX_POINTS)")
    a = p.parse_args(argv)
    print(HEADER)
    for path in a.recordings:
        reader = WindowReader(not a.whole, a.window_max_points)
        print(evaluate(path, reader=reader).row(), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
