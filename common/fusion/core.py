"""The fusion service's state machine, without any bus: messages in, messages out.

``FusionCore`` owns a :class:`WheelIntegrator` (odom→base_link) and a :class:`MapPoseFilter` (map→base_link)
and turns each input message into the output messages the service publishes:

* ``on_odometry(WheelOdometry)`` → (``fusion/odom``, ``fusion/pose``) PoseEstimates, always both, at the
  odometry rate; a flagged reading republishes the held pose with status ``'flagged: <why>'``.
* ``on_slam_pose(PoseEstimate)`` / ``on_map_to_odom(TransformMsg)`` → a :class:`CorrectionResult`.
* ``restore(odom_msg, pose_msg)`` continues from the latched outputs of a previous run.
* ``visual_odometry(PoseEstimate)``: with no wheel odometry, a slam/pose becomes fusion/odom and fusion/pose.

Statuses of ``fusion/pose``: 'ok' (a correction fused within ``stale_after_s``), 'odometry only' (none yet,
or stale), 'flagged: <why>' (this odometry reading or the last correction was refused).  ``fusion/odom``
says 'ok' or 'flagged: <why>'.  Not thread-safe: the service serialises calls with a lock.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from common.fusion.odometry import OdometryModel, OdometryStep, WheelIntegrator
from common.fusion.planar import covariance3, covariance6, from_transform, to_transform
from common.fusion.pose_filter import CorrectionError, CorrectionResult, FilterConfig, MapPoseFilter
from common.messages import BASE_LINK, MAP, ODOM, PoseEstimate, TransformMsg, WheelOdometry, pose_msg, transform_of


@dataclass
class FusionCounters:
    """What went wrong, by kind (the service copies these into its heartbeat)."""
    flagged: dict[str, int] = field(default_factory=dict)
    corrections_fused: int = 0
    corrections_rejected: int = 0
    corrections_unusable: int = 0

    def flag(self, kind: str) -> None:
        self.flagged[kind] = self.flagged.get(kind, 0) + 1


class FusionCore:
    def __init__(self, model: OdometryModel | None = None, config: FilterConfig | None = None):
        self.odometry = WheelIntegrator(model)
        self.filter = MapPoseFilter(config)
        self.counters = FusionCounters()
        self.last_step: OdometryStep | None = None
        self._pending_flag: str | None = None
        self.wheels_seen = False

    # ------------------------------------------------------------------------------ restart
    def restore(self, odom: PoseEstimate | None, pose: PoseEstimate | None) -> bool:
        """Continue from the latched ``fusion/odom`` (and ``fusion/pose``) of a previous run. Returns True
        when the odom pose was restored. The map pose is kept only if it came with the same stamp."""
        if odom is None or odom.header.frame_id != ODOM:
            return False
        o = from_transform(transform_of(odom))
        self.odometry.restore(o, covariance3(odom.covariance), odom.header.stamp_ns)
        self.filter.remember(odom.header.stamp_ns, o)
        if pose is not None and pose.header.frame_id == MAP and pose.header.stamp_ns == odom.header.stamp_ns:
            p = from_transform(transform_of(pose))
            corrected = not np.allclose(p, o, atol=1e-9) or pose.status == "ok"
            self.filter.restore(p, covariance3(pose.covariance), corrected)
        else:
            self.filter.restore(o, covariance3(odom.covariance), False)
        return True

    # ----------------------------------------------------------------------------- odometry
    def on_odometry(self, msg: WheelOdometry) -> tuple[PoseEstimate, PoseEstimate]:
        self.wheels_seen = True
        step = self.odometry.update(msg)
        self.last_step = step
        if step.ok:
            k = self.odometry.model.k_wheel_m
            self.filter.predict(step.stamp_ns, self.odometry.pose, self.odometry.cov, step.dl, step.dr,
                                step.track_width or 1.0, k * abs(step.dl), k * abs(step.dr))
            odom_status = "ok"
        else:
            self.counters.flag(step.kind)
            odom_status = f"flagged: {step.flag}"
        if not step.ok:
            pose_status = odom_status
        elif self._pending_flag is not None:
            pose_status, self._pending_flag = f"flagged: {self._pending_flag}", None
        elif self.filter.is_fresh(step.stamp_ns):
            pose_status = "ok"
        else:
            pose_status = "odometry only"
        # A flagged reading is stamped with the last good time: the held pose is not newer than that.
        stamp = step.stamp_ns if step.ok else (self.odometry.stamp_ns or step.stamp_ns)
        odom = pose_msg(to_transform(self.odometry.pose), covariance6(self.odometry.cov), stamp_ns=stamp,
                        frame_id=ODOM, child=BASE_LINK, status=odom_status, source_seq=msg.header.seq)
        pose = pose_msg(to_transform(self.filter.pose), covariance6(self.filter.cov), stamp_ns=stamp,
                        frame_id=MAP, child=BASE_LINK, status=pose_status, source_seq=msg.header.seq)
        return odom, pose

    # -------------------------------------------------------------------------- corrections
    def on_slam_pose(self, msg: PoseEstimate) -> CorrectionResult:
        """A localiser pose of base_link in map (ignored unless frame_id is map and status 'ok')."""
        if msg.header.frame_id != MAP or msg.child_frame_id != BASE_LINK:
            return self._unusable(f"slam/pose must be {BASE_LINK} in {MAP}, got {msg.child_frame_id} in "
                                  f"{msg.header.frame_id!r}")
        if msg.status != "ok":
            return CorrectionResult(False, f"localiser status {msg.status!r}")
        try:
            T = transform_of(msg)
            return self._count(self.filter.correct_pose(msg.header.stamp_ns, from_transform(T),
                                                        covariance3(msg.covariance)))
        except (CorrectionError, np.linalg.LinAlgError, ValueError) as e:
            return self._unusable(str(e))

    def visual_odometry(self, msg: PoseEstimate) -> tuple[PoseEstimate, PoseEstimate] | None:
        """Without wheels the localiser's own estimates are the odometry (map and odom coincide):
        (``fusion/odom``, ``fusion/pose``) from an 'ok' ``slam/pose``, or None once wheels were seen or
        for a pose that is not usable. Downstream, nothing changes."""
        if self.wheels_seen or msg.status != "ok" or msg.header.frame_id != MAP:
            return None
        T = transform_of(msg)
        if not np.all(np.isfinite(T)) or not np.all(np.isfinite(msg.covariance)):
            return None
        stamp, seq = msg.header.stamp_ns, msg.header.seq
        return (pose_msg(T, msg.covariance, stamp_ns=stamp, frame_id=ODOM, child=BASE_LINK, status="visual",
                         source_seq=seq),
                pose_msg(T, msg.covariance, stamp_ns=stamp, frame_id=MAP, child=BASE_LINK, status="ok",
                         source_seq=seq))

    def on_map_to_odom(self, msg: TransformMsg) -> CorrectionResult:
        if msg.header.frame_id != MAP or msg.child_frame_id != ODOM:
            return self._unusable(f"slam/map_to_odom must be {MAP}→{ODOM}, got {msg.header.frame_id!r}→"
                                  f"{msg.child_frame_id!r}")
        try:
            return self._count(self.filter.correct_map_to_odom(msg.header.stamp_ns,
                                                               from_transform(transform_of(msg))))
        except (CorrectionError, np.linalg.LinAlgError, ValueError) as e:
            return self._unusable(str(e))

    def _count(self, result: CorrectionResult) -> CorrectionResult:
        if result.accepted:
            self.counters.corrections_fused += 1
        elif not result.reason.startswith("duplicate"):
            self.counters.corrections_rejected += 1
            self._pending_flag = result.reason
        return result

    def _unusable(self, reason: str) -> CorrectionResult:
        self.counters.corrections_unusable += 1
        return CorrectionResult(False, f"unusable correction: {reason}")
