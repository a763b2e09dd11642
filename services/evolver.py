"""Fly evolver service: the Fly algorithm running continuously on the newest stereo frame.

Takes ``stereo/frame`` with latest-value semantics (frames that arrive while it works are skipped and
counted), the calibration ``stereo/calibration`` (latched), the odometry pose ``fusion/odom`` and the
sonar scan ``fusion/sonar``. Each new frame goes through :class:`common.fly.core.EvolverCore` (motion
compensation, re-scoring, settling until the population is good enough or ``--settle-ms`` is spent —
the same step ``flyslam eval`` runs) and its population is published on ``flies/population`` (and, with
the frame's grey left image, on ``flies/population/@image`` for the localiser); between
frames it keeps evolving and republishes at ``--publish-hz``, spending at most ``--duty`` of the wall
time and only while its CPU over the last second is under ``--cpu-budget`` of a core.
``--trace`` publishes each frame's stage times on ``trace/evolver``.

Degraded mode: while the evolver gets less than ``--degraded-share`` of the CPU time it asks for and the
machine has less than ``--free-cpu-floor`` of a core idle (overloaded: :class:`common.fly.scheduling.CpuGovernor`), it stops evolving between frames
and shortens each frame's settle in proportion, so frames are published sooner and the localiser gets
the CPU; the newest frame is always the one taken. Its heartbeat then says ``state: degraded``, counts
``degraded_frames`` and carries ``cpu_share``, ``cpu_used`` and ``cpu_free`` (the machine's idle cores) in its
rates.
"""
from __future__ import annotations

import dataclasses
import logging
import sys
import time

from common import messages as m
from common import streams as S
from common.config_args import add_config_arguments
from common.fly import EvolverConfig
from common.fly.core import EvolverCore, EvolverServiceConfig, FrameResult, warm_up
from services.base import config_or_exit, load_kernels_ahead, run_service, service_parser, survive

log = logging.getLogger("flyslam.evolver")
EVOLVER_FLAGS = ["population", "depth_min", "depth_max"]


def build_parser():
    p = service_parser("evolver", __doc__.splitlines()[0])
    add_config_arguments(p, EvolverConfig, only=EVOLVER_FLAGS, helps={
        "population": "number of flies", "depth_min": "nearest fly depth (m)",
        "depth_max": "farthest fly depth (m); inf allowed"})
    add_config_arguments(p, EvolverServiceConfig)
    p.add_argument("--threads", type=int, default=None, help="numba threads for the fitness kernel")
    p.add_argument("--trace", action="store_true", help="publish per-frame stage times on trace/evolver")
    return p


def body(node, args) -> int:
    if args.threads:
        import numba
        numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    run = config_or_exit(EvolverServiceConfig, args)
    core = EvolverCore(config_or_exit(EvolverConfig, args, only=EVOLVER_FLAGS), settle=run.settle_policy(),
                       seed=run.seed, sonar_weight=run.sonar_weight)
    calibration = node.latched(S.STEREO_CALIBRATION)
    node.subscribe(S.FUSION_ODOM, callback=lambda msg: core.on_odometry(msg.header.stamp_ns, m.transform_of(msg)))
    node.subscribe(S.FUSION_SONAR, callback=core.on_sonar)
    frames = node.subscribe_latest(S.STEREO_FRAME)
    out, with_image = node.publisher(S.FLIES_POPULATION), node.publisher(S.FLIES_WITH_IMAGE)
    trace = node.publisher(S.TRACE_EVOLVER) if args.trace else None
    governor = run.governor()
    last_publish, rest_until, window = 0.0, 0.0, (time.monotonic(), 0)
    frames_span = None        # (time, generation) at the first frame and at the newest
    while not node.stopping:
        if time.monotonic() - window[0] >= 1.0:
            node.rates["generations_per_s"] = (core.generation - window[1]) / (time.monotonic() - window[0])
            window = (time.monotonic(), core.generation)
            if frames_span is not None and frames_span[1][0] > frames_span[0][0]:
                # the run's mean while frames came: the last second's rate is 0 once they stop
                (t0, g0), (t1, g1) = frames_span
                node.rates["generations_per_s_while_frames"] = (g1 - g0) / (t1 - t0)
            report_governor(node, governor)
        now = time.monotonic()
        resting = now < rest_until                 # the duty cycle's pause after a generation between frames
        idle = resting or not core.has_population or not governor.optional_allowed()
        # Idle: block for the next frame (no polling; a frame ends a pause at once).
        frame = frames.wait(rest_until - now if resting else 0.05) if idle else frames.take()
        if frame is not None:
            with survive(node, "frame", log), governor.work():
                if calibration.get() is not None:
                    core.on_calibration(calibration.get())
                result = core.on_frame(frame, settle_scale=governor.settle_scale())
                if publish_frame(node, result, frame, out, with_image, trace):
                    last_publish = time.monotonic()
                    newest = (last_publish, core.generation)
                    frames_span = (frames_span[0] if frames_span else newest, newest)
                    node.rates["frames_skipped"] = float(frames.skipped)
                    node.counters.add("degraded_frames", int(governor.degraded))
        elif not idle:   # between frames: evolve with a duty cycle, republish at the configured rate
            t0 = time.monotonic()
            with survive(node, "evolve", log), governor.work():
                core.step()
                if time.monotonic() - last_publish >= 1.0 / run.publish_hz:
                    out.publish(core.population())
                    last_publish = time.monotonic()
            busy = time.monotonic() - t0
            if run.duty < 1.0:
                rest_until = time.monotonic() + busy * (1.0 / max(run.duty, 0.05) - 1.0)
    return 0


def report_governor(node, governor) -> None:
    """The heartbeat's view of the CPU: share obtained, CPU used, and the degraded state (logged on change)."""
    node.rates["cpu_share"] = round(governor.share, 3)
    node.rates["cpu_used"] = round(governor.spent, 3)
    if governor.free is not None:
        node.rates["cpu_free"] = round(governor.free, 3)
    state = "degraded" if governor.degraded else "running"
    if state != node.state:
        log.log(logging.WARNING if governor.degraded else logging.INFO,
                "%s: the evolver gets %.0f %% of the CPU time it asks for", state, 100 * governor.share)
        node.state = state


_COUNTER = {"no calibration": "frames_without_calibration", "bad calibration": "bad_calibration",
            "bad frame": "bad_frames"}


def publish_frame(node, result: FrameResult, frame: m.StereoFrame, out, with_image, trace) -> bool:
    """Publish a frame's population on ``with_image`` (flies/population/@image, the localiser's: first)
    and, without its image, on ``out`` (flies/population), and its trace; count and log a refused frame.
    True when published."""
    if result.population is None:
        node.counters.add(_COUNTER.get(result.reason.split(":")[0], "bad_frames"))
        log.log(logging.DEBUG if result.reason == "no calibration" else logging.WARNING,
                "frame %d: %s", frame.header.seq, result.reason)
        return False
    pop = result.population       # each publisher stamps its own seq into a header of seq 0: two headers
    without_image = dataclasses.replace(pop, image=None, header=dataclasses.replace(pop.header))
    with_image.publish(pop)
    out.publish(without_image)
    node.progress += 1
    node.counters.add("frames_without_odometry", int(result.without_odometry))
    node.rates["settle_generations"] = float(result.generations)
    if trace is not None:
        result.trace.published_ns = time.monotonic_ns()
        trace.publish(result.trace)
    return True


def load_kernels(args) -> None:
    """Before joining the bus (common.fly.core.warm_up): the first frame then pays for no kernel."""
    from common.fly import fitness, operators
    load_kernels_ahead(log, lambda: warm_up(config_or_exit(EvolverConfig, args, only=EVOLVER_FLAGS)),
                       "the first frame", probes=[fitness._fitness_kernel_serial, operators.plan_batch])


def main(argv=None) -> int:
    return run_service("evolver", build_parser(), body, argv, prepare=load_kernels)


if __name__ == "__main__":
    sys.exit(main())
