"""Localiser service (SLAM): registers each newest fly population against a map of keyframe populations.

Takes ``flies/population/@image`` (latest value: each frame's population with its grey left
image), the odometry pose ``fusion/odom`` as prior and the latched
``stereo/calibration``; publishes ``slam/pose`` (base_link in map with covariance; the status says when
a registration was rejected and odometry carried on, or that it is still relocalising) and
``slam/map_to_odom`` (REP-105), answers the queryable ``slam/map`` and writes the trajectory as TUM text
(``--tum``) and the map as ``map.mcap`` next to it (atomically, every ``map_period_s`` when it changed, and
on exit); ``--map FILE`` starts from a saved map, relocalising in it. The state machine is
:class:`common.slam.core.LocaliserCore`, the same one ``flyslam eval`` runs.

Restarts (the supervisor restarts a killed localiser with the same flags) lose nothing: the ``--tum``
file is never overwritten — the poses it already holds are kept ahead of this run's, each new pose is
appended as it is published and the whole file is rewritten atomically every ``tum_period_s`` with
the back-end's (optimised) trajectory.  On a restart (the supervisor sets ``FLYSLAM_RESTARTS`` > 0) the
run folder's ``map.mcap`` is the one the killed run saved: it is loaded (in preference to ``--map``) and
the localiser relocalises in it, near the ``slam/map_to_odom`` the bus still latches (the supervisor
holds it).  While the core's code and the map load (a second or more: numba, SciPy, GTSAM), a stand-in
(common.slam.standin) publishes 'relocalising: loading the map' poses from that map→odom and the
odometry, so a restarted localiser is heard from at once.  A fresh start into a folder an earlier run
wrote sets that run's trajectory and map aside (``*.previous.*``) instead of continuing them.
"""
from __future__ import annotations

import logging
import os
import sys
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from common import messages as m
from common import streams as S
from common.config_args import add_config_arguments
from common.pose_buffer import PoseBuffer
from common.slam.config import ArchiveConfig, LocaliserConfig, LocaliserServiceConfig
from common.slam.standin import StandInCore
from common.trajectory import TrajectoryFormatError, format_tum, parse_tum
from services.base import config_or_exit, load_kernels_ahead, run_service, service_parser

if TYPE_CHECKING:    # imported at run time by load_localiser, in a thread: it is the slow part of a start
    from common.slam.core import LocaliserCore, LocaliserOutput

log = logging.getLogger("flyslam.localiser")
LOCALISER_FLAGS = ["max_keyframes", "max_depth_m", "odometry", "loop_closure"]
RENAME = {"max_depth_m": "max-depth"}


def build_parser():
    p = service_parser("localiser", __doc__.splitlines()[0])
    add_config_arguments(p, LocaliserServiceConfig)
    add_config_arguments(p, ArchiveConfig, only=["max_archive_keyframes"])
    add_config_arguments(p, LocaliserConfig, only=LOCALISER_FLAGS, rename=RENAME, helps={
        "max_keyframes": "keyframes kept in the map (oldest dropped)",
        "max_depth_m": "flies farther than this (m, camera depth) are not used (default: 0.3 f B)",
        "odometry": "'wheels' (fusion/odom predicts) or 'visual' (no wheels: constant velocity)",
        "loop_closure": "register a new keyframe against old ones near it: a loop factor of the pose graph"})
    return p


class TrajectoryFile:
    """The ``--tum`` file of a run that may be restarted: what it holds is kept (a last line cut by a
    kill is dropped; an unreadable file is moved aside to ``<name>.unreadable``, never lost), new poses
    are appended one line at a time as they are published, and :meth:`rewrite` replaces the file
    atomically with the kept poses older than this run followed by this run's trajectory."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.kept_stamps, self.kept_poses = np.zeros(0, np.int64), np.zeros((0, 4, 4))
        self._fh = None
        if not self.path.exists():
            return
        try:
            text = self.path.read_text()
            if text and not text.endswith("\n"):
                text = text[: text.rfind("\n") + 1]          # a line cut short by a kill
            self.kept_stamps, self.kept_poses = parse_tum(text, str(self.path))
        except (OSError, UnicodeDecodeError, TrajectoryFormatError) as e:
            aside = self.path.with_name(self.path.name + ".unreadable")
            os.replace(self.path, aside)
            log.warning("%s is unreadable (%s): moved to %s, starting a new one", self.path, e, aside.name)
            return
        if len(self.kept_stamps):
            log.info("continuing %s: %d poses kept", self.path, len(self.kept_stamps))

    def append(self, stamp_ns: int, T_map_base: np.ndarray) -> None:
        if self._fh is None:
            self._fh = open(self.path, "a")
        self._fh.write(format_tum(np.array([stamp_ns], np.int64), T_map_base[None]))
        self._fh.flush()

    def rewrite(self, stamps: np.ndarray, poses: np.ndarray) -> int:
        """The kept poses before ``stamps[0]`` and then ``stamps``/``poses``, atomically; the pose count."""
        older = self.kept_stamps < stamps[0] if len(stamps) else np.ones(len(self.kept_stamps), bool)
        all_stamps = np.concatenate([self.kept_stamps[older], np.asarray(stamps, np.int64)])
        all_poses = np.concatenate([self.kept_poses[older], np.asarray(poses, float).reshape(-1, 4, 4)])
        self.close()
        tmp = self.path.with_name(self.path.name + ".tmp")
        tmp.write_text(format_tum(all_stamps, all_poses))
        os.replace(tmp, self.path)
        return len(all_stamps)

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


def is_restart() -> bool:
    """Whether the supervisor restarted this service (FLYSLAM_RESTARTS > 0) rather than started it."""
    return os.environ.get("FLYSLAM_RESTARTS", "0").strip() not in ("", "0")


def set_aside_earlier_run(*paths: Path | None) -> None:
    """A fresh start into a folder an earlier run wrote: its trajectory and map are moved to
    ``<stem>.previous<suffix>`` (kept, never continued: that robot was somewhere else)."""
    for path in paths:
        if path is not None and path.exists():
            aside = path.with_name(f"{path.stem}.previous{path.suffix}")
            os.replace(path, aside)
            log.warning("%s is an earlier run's: moved to %s", path, aside.name)


def starting_map(run: LocaliserServiceConfig, map_path: Path | None):
    """(map data or None, restarted): on a restart the run folder's map.mcap, else ``--map``; raises
    MapFileError for a bad ``--map`` (a bad run-folder map is logged and ignored: the run goes on)."""
    from common.slam.mapfile import MapFileError, load_map     # (mcap: imported in the loading thread)

    if map_path is not None and map_path.exists() and is_restart():
        try:
            data = load_map(map_path)
            log.info("restart: continuing the run's map %s (%d keyframes)", map_path, len(data.keyframes))
            return data, True
        except MapFileError as e:
            log.warning("restart: %s; not using it", e)
    if run.map:
        data = load_map(run.map)
        log.info("starting from %s: %d keyframes, %d edges", run.map, len(data.keyframes), len(data.edges))
        return data, False
    return None, False


def load_localiser(run: LocaliserServiceConfig, config: LocaliserConfig, map_path: Path | None):
    """The slow part of a start, run beside the stand-in: import the core (numba, SciPy, GTSAM: a second
    or more), load its kernels (common.slam.core.warm_up) and read the starting map.  (LocaliserCore
    class, map data or None, restarted)."""
    from common.slam.core import LocaliserCore, warm_up

    load_kernels_ahead(log, lambda: warm_up(config), "the first population")
    return (LocaliserCore, *starting_map(run, map_path))


def latched_map_to_odom(node) -> np.ndarray | None:
    """Where odom was in the map when the killed run stopped (the supervisor latches it), or None."""
    for _ in range(3):      # (a query sent before the session has joined the bus finds nobody)
        latched = node.query_latest(S.SLAM_MAP_TO_ODOM, timeout=0.3)
        if latched is not None:
            return m.transform_of(latched)
        time.sleep(0.1)
    return None


def body(node, args) -> int:
    run = config_or_exit(LocaliserServiceConfig, args)
    config = config_or_exit(LocaliserConfig, args, only=LOCALISER_FLAGS, rename=RENAME)
    archive = config_or_exit(ArchiveConfig, args, only=["max_archive_keyframes"])
    map_path = Path(run.tum).parent / "map.mcap" if run.tum else None
    if not is_restart():
        set_aside_earlier_run(Path(run.tum) if run.tum else None, map_path)
    loading: Future = ThreadPoolExecutor(1, thread_name_prefix="load").submit(load_localiser, run, config, map_path)
    hint = latched_map_to_odom(node) if is_restart() else None
    odometry = PoseBuffer(maxlen=1000)
    stand_in, core = StandInCore(hint, odometry), None
    tum = TrajectoryFile(run.tum) if run.tum else None
    lock = threading.Lock()

    def on_odom(msg: m.PoseEstimate) -> None:
        with lock:
            odometry.add(msg.header.stamp_ns, m.transform_of(msg))

    def serve_map():
        with lock:
            return core.map_message(time.time_ns()) if core is not None else None

    node.subscribe(S.FUSION_ODOM, callback=on_odom)
    calibration = node.latched(S.STEREO_CALIBRATION)
    node.queryable(S.SLAM_MAP, serve_map)
    populations = node.subscribe_latest(S.FLIES_WITH_IMAGE)
    pubs = node.publisher(S.SLAM_POSE), node.publisher(S.SLAM_MAP_TO_ODOM)
    last_tum = last_map = time.monotonic()
    map_changed = False
    restarts_seen = 0
    while not node.stopping:
        if core is None and loading.done():
            from common.slam.mapfile import MapFileError     # (loaded by now)
            try:
                core_class, initial_map, restarted = loading.result()
            except MapFileError as e:
                log.error("%s", e)
                return 2
            if restarted:
                log.info("restart: relocalising %s (%d stand-in poses while loading)",
                         "near the latched map->odom" if hint is not None else "in the whole map", stand_in.published)
            with lock:
                core = core_class(config, seed=run.seed, odometry=odometry, initial_map=initial_map,
                                  hint_map_to_odom=hint if restarted else None, archive=archive)
        pop = populations.wait(timeout=0.5 if core is not None else 0.05)
        if pop is None:
            continue
        with lock:
            current = core if core is not None else stand_in
            if not current.has_calibration and calibration.get() is not None:
                current.on_calibration(calibration.get())
            if core is None:
                stand_in_pose = stand_in.on_population(pop)
            else:
                out = core.on_population(pop)
        if core is None:
            if stand_in_pose is not None:
                node.counters.add("relocalising")
                pubs[0].publish(stand_in_pose)
            continue
        publish(node, out, pop, *pubs)
        node.rates["keyframes"] = float(len(core.keyframes))
        if out.estimate is not None:
            map_changed |= out.estimate.keyframe_added
            if tum is not None and core.keyframes:     # the trajectory starts with the map
                tum.append(out.pose.header.stamp_ns, out.estimate.T_map_base)
        if core.localiser is not None:      # the back-end's trouble, as counters in the heartbeat
            node.rates["graph_failed_updates"] = float(core.localiser.graph_failed_updates)
            node.rates["graph_unsolved_keyframes"] = float(core.localiser.graph_failures)
        if core.localiser is not None and core.localiser.map_restarts > restarts_seen:
            # the map started again (common.slam.localiser._first_fix_too_late): its first origin
            # leaves the trajectory file and the map now, not at the next periodic rewrite
            node.counters.add("map_restarts", core.localiser.map_restarts - restarts_seen)
            restarts_seen = core.localiser.map_restarts
            log.info("%s", out.estimate.status)
            map_changed = True
            last_tum = last_map = 0.0
        if tum is not None and time.monotonic() - last_tum > run.tum_period_s:
            with lock:
                tum.rewrite(*core.trajectory())
            last_tum = time.monotonic()
        if map_path is not None and map_changed and time.monotonic() - last_map > run.map_period_s:
            with lock:
                save_map_logged(core, map_path, quiet=True)
            last_map, map_changed = time.monotonic(), False
    if core is None:        # stopped while loading: nothing of this run to write
        return 0
    if tum is not None:
        total = tum.rewrite(*core.trajectory())
        log.info("wrote %d poses to %s (%d of this run)", total, run.tum, core.localised)
    if map_path is not None:
        save_map_logged(core, map_path)
    return 0


def save_map_logged(core: LocaliserCore, path: Path, quiet: bool = False) -> None:
    """Write map.mcap; a failure (disk full, bad folder) is logged, never fatal."""
    from common.slam.mapfile import MapFileError
    try:
        if core.save_map(path) and not quiet:
            log.info("wrote the map (%d keyframes) to %s", len(core.localiser.map_keyframes()), path)
    except (MapFileError, OSError) as e:
        log.warning("could not write the map to %s: %s", path, e)


def publish(node, out: LocaliserOutput, pop: m.FlyPopulation, pose_pub, tf_pub) -> None:
    """Publish a localised population's pose and map→odom (while relocalising: the pose only, with
    its status); count and log a refused one."""
    if out.estimate is None and out.pose is not None:
        node.counters.add("relocalising")
        pose_pub.publish(out.pose)
        return
    if out.estimate is None:
        if out.reason != "republished":
            node.counters.add("populations_without_calibration" if out.reason == "no calibration"
                              else "bad_populations")
            log.log(logging.DEBUG if out.reason == "no calibration" else logging.WARNING,
                    "population %d: %s", pop.source_seq, out.reason)
        return
    node.counters.add("registrations_ok" if out.estimate.registered else "registrations_rejected")
    node.counters.add("keyframes", int(out.estimate.keyframe_added))
    pose_pub.publish(out.pose)
    if out.map_to_odom is not None:      # none before the map's first keyframe
        tf_pub.publish(out.map_to_odom)
    node.progress += 1


def main(argv=None) -> int:
    return run_service("localiser", build_parser(), body, argv)


if __name__ == "__main__":
    sys.exit(main())
