"""What a restarted localiser publishes while its core is still loading (no I/O, light to import).

A killed localiser is restarted by the supervisor, and the new process needs a second or more to load
the numba, SciPy and GTSAM code of :class:`common.slam.core.LocaliserCore` and the saved map.  Meanwhile
:class:`StandInCore` answers each population as the core answers while it relocalises: a ``slam/pose``
at the pose the last published map→odom (latched by the supervisor) and the odometry give, with status
``'relocalising: loading the map'`` and the unknown covariance, and no ``map_to_odom``.  Fusion fuses
only status 'ok' and the planner keeps the latched map→odom, so nothing downstream takes it for a fix;
the viewer and the run's report see the localiser alive at once.  The service builds the core on the
stand-in's odometry buffer, so no reading is lost in the hand-over.
"""
from __future__ import annotations

import numpy as np

from common import messages as m
from common.core_inputs import LatchedInputs
from common.pose_buffer import PoseBuffer

UNKNOWN_COVARIANCE = np.eye(6) * 1e4    # a relocalising pose says nothing
LOADING_STATUS = "relocalising: loading the map"


class StandInCore(LatchedInputs):
    """Populations in, 'loading' poses out, until the real core takes over.  ``hint_map_to_odom``: the
    latched map→odom (None: nothing is published, there is no pose to offer)."""

    def __init__(self, hint_map_to_odom: np.ndarray | None, odometry: PoseBuffer | None = None):
        super().__init__(odometry if odometry is not None else PoseBuffer(maxlen=1000))
        self.hint = None if hint_map_to_odom is None else np.asarray(hint_map_to_odom, float)
        self.published = 0

    def on_population(self, pop: m.FlyPopulation) -> m.PoseEstimate | None:
        if self.hint is None:
            return None
        calib = self._calibration_msg
        T_odom_base = self.odom_base_of(pop, calib.T_base_camera if calib is not None else None)
        if T_odom_base is None:
            return None
        self.published += 1
        return m.pose_msg(self.hint @ T_odom_base, UNKNOWN_COVARIANCE, stamp_ns=pop.header.stamp_ns,
                          status=LOADING_STATUS, source_seq=pop.source_seq)
