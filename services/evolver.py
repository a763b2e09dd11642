"""Fly evolver service: the Fly algorithm running continuously on the newest stereo frame.

Takes ``stereo/frame`` with latest-value semantics (frames that arrive while it works are skipped and
counted), the calibration from ``stereo/calibration`` (latched), the odometry pose from ``fusion/odom``
and the sonar scan from ``fusion/sonar``. On each new frame it moves every fly by the camera's motion
since the previous frame (proprioceptive fusion), re-scores the population on the new images and evolves
it until it is *good enough* — its mean fitness is back to ``--recovery`` × what it was on the previous
frame, after at least ``--min-generations`` — or ``--settle-ms`` has passed, whichever comes first; then
it publishes ``flies/population`` tagged with that frame's seq and stamp (the pose latency of the whole
pipeline starts here, so the publication is as early as the population allows). Between frames it keeps
evolving and republishes at ``--publish-hz`` (anytime: the population is always the current answer).
``--duty`` caps the share of one core's time it spends evolving between frames, so the other services on
a small machine — above all the localiser registering the population just published — keep theirs.

``--trace`` also publishes, per frame, when it was taken, decoded, re-scored and published
(``trace/evolver``, an EvolverTrace message, monotonic ns) so that bench/pipeline.py can break the latency
down.
"""
from __future__ import annotations

import logging
import sys
import threading
import time

from common import messages as m
from common.camera import CalibrationError
from common.fly import EvolverConfig, FlyEvolver
from common.fly.scheduling import SettlePolicy, population_quality, settle
from common.geometry import invert
from common.images import frame_images
from common.pose_buffer import PoseBuffer
from services.base import run_service, service_parser

log = logging.getLogger("flyslam.evolver")


def build_parser():
    p = service_parser("evolver", __doc__.splitlines()[0])
    p.add_argument("--population", type=int, default=5000, help="number of flies")
    p.add_argument("--depth-min", type=float, default=0.3, help="nearest fly depth (m)")
    p.add_argument("--depth-max", type=float, default=30.0, help="farthest fly depth (m); inf allowed")
    p.add_argument("--settle-ms", type=float, default=40.0,
                   help="longest evolution on a new frame before publishing (ms)")
    p.add_argument("--min-generations", type=int, default=1,
                   help="generations on a new frame before its population may be published")
    p.add_argument("--recovery", type=float, default=0.95,
                   help="publish a new frame's population once its mean fitness is back to this fraction of "
                        "the previous frame's (1 = full recovery; 0 = after --min-generations)")
    p.add_argument("--publish-hz", type=float, default=10.0, help="republish rate between frames")
    p.add_argument("--duty", type=float, default=0.7, help="fraction of wall time spent evolving between frames")
    p.add_argument("--threads", type=int, default=None, help="numba threads for the fitness kernel")
    p.add_argument("--sonar-weight", type=float, default=0.0, help="weight of the sonar fitness term (0 = off)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--trace", action="store_true", help="publish per-frame stage times on trace/evolver")
    return p


class Inputs:
    """What Zenoh threads deliver between frames: calibration, odometry history, newest sonar scan."""

    def __init__(self):
        self.lock = threading.Lock()
        self.calibration_msg: m.StereoCalibrationMsg | None = None
        self.odom = PoseBuffer(maxlen=400)
        self.sonar: m.SonarScan | None = None

    def on_calibration(self, msg):
        with self.lock:
            self.calibration_msg = msg

    def on_odom(self, msg: m.PoseEstimate):
        with self.lock:
            self.odom.add(msg.header.stamp_ns, m.transform_of(msg))

    def on_sonar(self, msg: m.SonarScan):
        with self.lock:
            self.sonar = msg


def body(node, args) -> int:
    if args.threads:
        import numba
        numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    inputs = Inputs()
    node.subscribe("stereo/calibration", m.StereoCalibrationMsg, inputs.on_calibration)
    node.subscribe("fusion/odom", m.PoseEstimate, inputs.on_odom)
    node.subscribe("fusion/sonar", m.SonarScan, inputs.on_sonar)
    frames = node.subscribe_latest("stereo/frame", m.StereoFrame)
    out = node.publisher("flies/population")
    trace = node.publisher("trace/evolver") if args.trace else None
    settle_policy = SettlePolicy(args.settle_ms / 1000, args.min_generations, args.recovery)
    calib_msg = node.query_latest("stereo/calibration", m.StereoCalibrationMsg, timeout=1.0)
    if calib_msg is not None:
        inputs.on_calibration(calib_msg)

    evolver = None
    calib = None
    used_calib_msg = None
    last_T_odom_cam = None
    current = None           # (seq, stamp, T_odom_cam or None) of the frame the flies were last evaluated on
    last_publish = 0.0
    generations_window = (time.monotonic(), 0)
    config = EvolverConfig(population=args.population, depth_min=args.depth_min, depth_max=args.depth_max)

    def publish():
        seq, stamp, T_odom_cam = current
        out.publish(m.FlyPopulation(positions=evolver.positions, fitness=evolver.fitness,
                                    generation=int(evolver.generation), source_seq=int(seq),
                                    T_odom_camera=T_odom_cam,
                                    header=m.header(0, stamp, m.CAMERA_LEFT_OPTICAL)))

    while not node.stopping:
        now = time.monotonic()
        if evolver is not None and now - generations_window[0] >= 1.0:
            node.rates["generations_per_s"] = (evolver.generation - generations_window[1]) / (now - generations_window[0])
            generations_window = (now, evolver.generation)
        frame = frames.take()
        if frame is None and current is None:
            node.sleep(0.005)
            continue
        if frame is not None:
            with inputs.lock:
                cmsg = inputs.calibration_msg
            if cmsg is None:
                # A source publishes its calibration rarely (a replay: once); ask its latched publisher.
                cmsg = node.query_latest("stereo/calibration", m.StereoCalibrationMsg, timeout=0.5)
                if cmsg is not None:
                    inputs.on_calibration(cmsg)
            if cmsg is None:
                node.counters.add("frames_without_calibration")
                continue
            if cmsg is not used_calib_msg:
                try:
                    new_calib = m.calibration_from_msg(cmsg)
                except CalibrationError as e:
                    node.counters.add("bad_calibration")
                    log.error("calibration rejected: %s", e)
                    continue
                if calib is None or (new_calib.width, new_calib.height, new_calib.fx, new_calib.baseline) != \
                        (calib.width, calib.height, calib.fx, calib.baseline):
                    calib = new_calib
                    evolver = FlyEvolver(calib, config, seed=args.seed)
                    if args.sonar_weight > 0:
                        _attach_sonar(evolver, inputs, calib, args.sonar_weight)
                    last_T_odom_cam = None
                    current = None
                    log.info("calibration %dx%d f=%.1f B=%.3f: %d flies", calib.width, calib.height, calib.fx,
                             calib.baseline, args.population)
                used_calib_msg = cmsg
            t_take = time.monotonic_ns()
            try:
                left, right = frame_images(frame)
                calib.check_image(left, "stereo frame")
            except (m.DecodeError, CalibrationError) as e:
                node.counters.add("bad_frames")
                log.warning("frame %d rejected: %s", frame.header.seq, e)
                continue
            t_decoded = time.monotonic_ns()
            reference = population_quality(evolver.fitness) if current is not None else None
            with inputs.lock:
                T_odom_base = inputs.odom.at(frame.header.stamp_ns)
            T_odom_cam = None if T_odom_base is None else T_odom_base @ calib.T_base_camera
            if T_odom_cam is not None and last_T_odom_cam is not None:
                evolver.move_flies(invert(T_odom_cam) @ last_T_odom_cam, rescore=False)   # T_new_old; set_images re-scores
            elif last_T_odom_cam is not None:
                node.counters.add("frames_without_odometry")
            last_T_odom_cam = T_odom_cam if T_odom_cam is not None else last_T_odom_cam
            evolver.set_images(left, right)
            current = (frame.header.seq, frame.header.stamp_ns, T_odom_cam)
            t_ready = time.monotonic_ns()
            generations = settle(evolver, reference, settle_policy)
            publish()
            t_published = time.monotonic_ns()
            last_publish = time.monotonic()
            node.progress += 1
            node.rates["frames_skipped"] = float(frames.skipped)
            node.rates["settle_generations"] = float(generations)
            if trace is not None:
                trace.publish(m.EvolverTrace(
                    take_ns=t_take, decoded_ns=t_decoded, ready_ns=t_ready, published_ns=t_published,
                    generations=int(generations), reference=reference,
                    quality=population_quality(evolver.fitness),
                    header=m.header(frame.header.seq, frame.header.stamp_ns, frame.header.frame_id)))
            continue
        # Between frames: evolve with a duty cycle, republish at the configured rate.
        t0 = time.monotonic()
        evolver.step(1)
        busy = time.monotonic() - t0
        if time.monotonic() - last_publish >= 1.0 / args.publish_hz:
            publish()
            last_publish = time.monotonic()
        if args.duty < 1.0:
            node.sleep(busy * (1.0 / max(args.duty, 0.05) - 1.0))
    return 0


def _attach_sonar(evolver, inputs: Inputs, calib, weight: float) -> None:
    """Plug the sonar fitness term (common.fusion.sonar_term) into the evolver, fed by the newest scan."""
    from common.fusion.sonar import SonarScanError
    from common.fusion.sonar_term import SonarTerm

    term = SonarTerm()
    seen = {"scan": None}

    def fn(positions):
        with inputs.lock:
            scan = inputs.sonar
        if scan is not None and scan is not seen["scan"]:
            seen["scan"] = scan
            try:
                term.update(scan, calib.T_base_camera)
            except SonarScanError as e:
                log.warning("sonar scan ignored: %s", e)
        return term(positions)

    evolver.add_fitness_term("sonar", fn, weight)


def main(argv=None) -> int:
    return run_service("evolver", build_parser(), body, argv)


if __name__ == "__main__":
    sys.exit(main())
