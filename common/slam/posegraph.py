"""Keyframe pose graph on GTSAM: keyframe poses as nodes, odometry and fly-registration factors as
edges, robust kernels so that a wrong registration or a wheel-slip burst loses the vote.

Poses are ``T_map_base`` 4×4 numpy transforms; a relative measurement ``T_i_j`` maps keyframe j's
base_link into keyframe i's (``T_map_j ≈ T_map_i @ T_i_j``).

Covariances (in and out) are 6×6 over flyslam's tangent order (x, y, z, rx, ry, rz): a *right*
perturbation ``T = T̂ · Exp(δ)``, so the translation and the rotation vector are both expressed in the
pose's own base_link (for a relative measurement: in keyframe j's frame).  For a level robot and small
errors, rz is the yaw error and rx, ry roll and pitch about the body axes.  GTSAM's Pose3 tangent is the
same right perturbation with the blocks swapped, (rx, ry, rz, x, y, z); this module converts at the
boundary and nowhere else.  :meth:`PoseGraph.marginal_covariance` can also rotate the result into the
map's axes (``frame="map"``: position error along map x, y, z, rotation error about map axes).  Marginals
come from the kernel-weighted information: an inlier's weight below 1 makes them slightly pessimistic.

Robust kernels act on the Mahalanobis norm of a factor's whole 6-D residual (GTSAM's block reweighting):
``k`` is in standard deviations.  Cauchy (default) leaves a far outlier a pull of ≈ k²/r (r its
whitened residual): small, and :meth:`PoseGraph.remove_downweighted` takes it away.  Huber's pull stays
k, so a confident wrong registration beats a soft odometry chain.  Redescending kernels (Geman-McClure,
DCS) were not chosen: they also reject a correct loop closure whose accumulated drift is many of its
sigmas at the linearisation point.  A kernel needs a linearisation point near the truth: initialise a new
keyframe from what the registrations say (the registered pose), not from odometry they contradict,
or the consistent factors look like the outliers.

Optimisation is incremental (iSAM2, a Gauss-Newton step per update, repeated until the error settles)
or a batch Levenberg-Marquardt over the whole graph, after which iSAM2 restarts from the batch answer.
An update that raises may leave iSAM2 half-changed, so the next optimise rebuilds it from the whole
graph (batch).  iSAM2 factorises by Cholesky until that fails, then by QR (slower, so only then): a
confident registration tens of metres long beside soft visual odometry made Cholesky report an
indeterminate system that QR and Levenberg-Marquardt solve.
A keyframe enters the optimiser with its first factor.  A factor can be removed by its handle; keyframes
are not (a corridor run holds hundreds, well within iSAM2's incremental cost), and one that loses its
last factor keeps its last pose.
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

# flyslam (x, y, z, rx, ry, rz) <-> GTSAM Pose3 (rx, ry, rz, x, y, z): the same permutation both ways.
_SWAP = np.r_[3:6, 0:3]

KINDS = ("odometry", "registration", "prior")
DEFAULT_K = {"cauchy": 3.0, "huber": 3.0}
# A weak level-robot prior: 1 cm on z, ~0.3° on roll and pitch, nothing on x, y, yaw.
PLANAR_SIGMAS = (0.01, 0.005, 0.005)
_FREE_SIGMA = 1e4
_GTSAM_ERRORS = (RuntimeError, IndexError, ValueError)   # what GTSAM's bindings raise for a bad update


class PoseGraphError(ValueError):
    """Bad input to the pose graph or an optimisation that cannot be solved; the message says which."""


@dataclass
class Edge:
    """A factor as the graph holds it: ``T_i_j`` and its covariance (flyslam order, frame j).
    A prior has ``i == j`` and ``T_i_j`` is the prior pose ``T_map_i``."""
    i: int
    j: int
    T_i_j: np.ndarray
    cov: np.ndarray
    kind: str
    robust: bool = False


@dataclass
class FactorReport:
    """What the optimised graph thinks of one factor: χ² of its residual under its own covariance
    (no kernel), the kernel's weight there (1 = fully believed) and whether that weight is below the
    graph's ``downweight_below``."""
    handle: int
    edge: Edge
    chi2: float
    weight: float
    downweighted: bool


def to_gtsam_cov(cov6) -> np.ndarray:
    """A flyslam-order 6×6 covariance in GTSAM's Pose3 tangent order (and back: the map is its own inverse)."""
    c = np.asarray(cov6, dtype=float)
    return c[np.ix_(_SWAP, _SWAP)]


# z (m) and roll/pitch (rad) sigmas of a planar measurement in a 6-DoF graph: it says nothing of them
UNCONSTRAINED_SIGMA = (10.0, 1.0)


def planar_covariance(cov3, sigma_z: float = 1e-3, sigma_roll_pitch: float = 1e-3) -> np.ndarray:
    """6×6 flyslam-order covariance of a planar (x, y, yaw) measurement with a 3×3 covariance, the
    out-of-plane components (z, roll, pitch) given small independent sigmas."""
    c3 = np.asarray(cov3, dtype=float)
    if c3.shape != (3, 3):
        raise PoseGraphError(f"a planar covariance must be 3×3 over (x, y, yaw), got shape {c3.shape}")
    cov = np.diag([0.0, 0.0, sigma_z**2, sigma_roll_pitch**2, sigma_roll_pitch**2, 0.0])
    cov[np.ix_([0, 1, 5], [0, 1, 5])] = c3
    return cov


def _check_transform(T, what: str) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise PoseGraphError(f"{what} must be a 4×4 transform, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise PoseGraphError(f"{what} is not finite")
    R = T[:3, :3]
    if (np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or abs(np.linalg.det(R) - 1.0) > 1e-6
            or np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9):
        raise PoseGraphError(f"{what} is not a rigid transform (rotation not orthonormal or bad last row)")
    return T


def _check_cov(cov, what: str) -> np.ndarray:
    c = np.asarray(cov, dtype=float)
    if c.shape != (6, 6):
        raise PoseGraphError(f"{what} must be 6×6 over (x, y, z, rx, ry, rz), got shape {c.shape}")
    if not np.all(np.isfinite(c)):
        raise PoseGraphError(f"{what} is not finite")
    if np.abs(c - c.T).max() > 1e-9 * max(1.0, np.abs(c).max()):
        raise PoseGraphError(f"{what} is not symmetric")
    if np.linalg.eigvalsh(c).min() <= 0.0:
        raise PoseGraphError(f"{what} is not positive definite (give an unconstrained axis a large variance)")
    return c


class PoseGraph:
    """Keyframe pose graph (see the module docstring for frames, tangent order and kernels).

    ``robust``: 'cauchy' (a far outlier's pull vanishes) or 'huber' (bounded pull); ``k`` its width in
    standard deviations.  ``planar``: every keyframe gets a weak prior holding z at ``planar_z`` and roll,
    pitch at 0 (sigmas ``planar_sigmas`` = (z m, roll rad, pitch rad)), x, y and yaw stay free.
    ``downweight_below``: a factor whose kernel weight falls below this is reported as down-weighted."""

    def __init__(self, robust: str = "cauchy", k: float | None = None, planar: bool = False,
                 planar_z: float = 0.0, planar_sigmas=PLANAR_SIGMAS, downweight_below: float = 0.25,
                 relinearize_threshold: float = 1e-3):
        if robust not in DEFAULT_K:
            raise PoseGraphError(f"robust kernel {robust!r}: expected one of {', '.join(DEFAULT_K)}")
        self.k = float(DEFAULT_K[robust] if k is None else k)
        if not self.k > 0:
            raise PoseGraphError(f"kernel width k must be > 0, got {k}")
        self.robust = robust
        self.planar = bool(planar)
        self.planar_z = float(planar_z)
        self.planar_sigmas = tuple(float(s) for s in planar_sigmas)
        self.downweight_below = float(downweight_below)
        self._relin = float(relinearize_threshold)
        self._estimator = (gtsam.noiseModel.mEstimator.Cauchy(self.k) if robust == "cauchy"
                           else gtsam.noiseModel.mEstimator.Huber(self.k))
        self._initial: dict[int, np.ndarray] = {}     # keyframe id -> initial T_map_base
        self._in_solver: set[int] = set()
        self._edges: dict[int, Edge] = {}             # handle -> edge (planar priors are not edges)
        self._factors: dict[int, gtsam.NonlinearFactor] = {}
        self._planar_factors: dict[int, gtsam.NonlinearFactor] = {}
        self._solver_index: dict[object, int] = {}    # handle or ("planar", id) -> iSAM2 factor index
        self._pending: list[object] = []              # handles / ("planar", id) not yet in iSAM2
        self._removed_indices: list[int] = []
        self._next_handle = 0
        self._estimate: gtsam.Values | None = None
        self._has_prior = False
        self._factorization = "CHOLESKY"
        self._isam = self._new_isam()
        self._isam_broken = False      # an update raised: iSAM2's state is unknown until a batch rebuild
        self.failed_updates = 0        # iSAM2 updates that raised (each followed by a rebuild, by QR)

    # ------------------------------------------------------------------------------- building

    def _new_isam(self) -> gtsam.ISAM2:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self._relin)
        params.relinearizeSkip = 1          # kernel weights are recomputed whenever a pose moves
        params.setFactorization(self._factorization)
        return gtsam.ISAM2(params)

    @staticmethod
    def _key(kf_id: int) -> int:
        return gtsam.symbol("k", int(kf_id))

    def add_keyframe(self, kf_id: int, T_initial) -> None:
        """A new node at ``T_initial`` (T_map_base), its linearisation point until the first optimise."""
        kf_id = int(kf_id)
        if kf_id < 0:
            raise PoseGraphError(f"keyframe id must be >= 0, got {kf_id}")
        if kf_id in self._initial:
            raise PoseGraphError(f"keyframe {kf_id} is already in the graph")
        self._initial[kf_id] = _check_transform(T_initial, f"keyframe {kf_id}'s initial pose").copy()
        if self.planar:
            T = self._initial[kf_id]
            yaw = np.arctan2(T[1, 0], T[0, 0])
            level = gtsam.Pose3(gtsam.Rot3.Yaw(yaw), gtsam.Point3(T[0, 3], T[1, 3], self.planar_z))
            sz, sr, sp = self.planar_sigmas
            sig = np.array([sr, sp, _FREE_SIGMA, _FREE_SIGMA, _FREE_SIGMA, sz])   # GTSAM order
            tag = ("planar", kf_id)
            self._planar_factors[kf_id] = gtsam.PriorFactorPose3(self._key(kf_id), level,
                                                                 gtsam.noiseModel.Diagonal.Sigmas(sig))
            self._pending.append(tag)

    def _require(self, kf_id: int, what: str) -> int:
        kf_id = int(kf_id)
        if kf_id not in self._initial:
            raise PoseGraphError(f"{what}: keyframe {kf_id} is not in the graph (add_keyframe first)")
        return kf_id

    def _noise(self, cov6: np.ndarray, robust: bool):
        gaussian = gtsam.noiseModel.Gaussian.Covariance(to_gtsam_cov(cov6))
        return gtsam.noiseModel.Robust.Create(self._estimator, gaussian) if robust else gaussian

    def _add(self, edge: Edge, factor) -> int:
        handle = self._next_handle
        self._next_handle += 1
        self._edges[handle] = edge
        self._factors[handle] = factor
        self._pending.append(handle)
        return handle

    def add_prior(self, kf_id: int, T, cov6) -> int:
        """Anchor keyframe ``kf_id`` at ``T`` (T_map_base) with covariance ``cov6``; returns a handle.
        At least one prior fixes the map frame (the graph's gauge)."""
        kf_id = self._require(kf_id, "add_prior")
        T = _check_transform(T, "prior pose")
        cov = _check_cov(cov6, "prior covariance")
        self._has_prior = True
        return self._add(Edge(kf_id, kf_id, T.copy(), cov.copy(), "prior", False),
                         gtsam.PriorFactorPose3(self._key(kf_id), gtsam.Pose3(T), self._noise(cov, False)))

    def _between(self, i, j, T_i_j, cov6, kind: str, robust: bool) -> int:
        i, j = self._require(i, f"add_{kind}"), self._require(j, f"add_{kind}")
        if i == j:
            raise PoseGraphError(f"add_{kind}: a factor between keyframe {i} and itself")
        T = _check_transform(T_i_j, f"{kind} T_{i}_{j}")
        cov = _check_cov(cov6, f"{kind} covariance")
        return self._add(Edge(i, j, T.copy(), cov.copy(), kind, bool(robust)),
                         gtsam.BetweenFactorPose3(self._key(i), self._key(j), gtsam.Pose3(T),
                                                  self._noise(cov, robust)))

    def add_odometry(self, i: int, j: int, T_i_j, cov6, robust: bool = True) -> int:
        """Wheel or visual odometry from keyframe i to j; robust by default, so a wheel-slip burst that
        the registrations contradict is outvoted."""
        return self._between(i, j, T_i_j, cov6, "odometry", robust)

    def add_registration(self, i: int, j: int, T_i_j, cov6, robust: bool = True) -> int:
        """A fly-population registration: keyframe j's population registered against keyframe i's."""
        return self._between(i, j, T_i_j, cov6, "registration", robust)

    def add_edge(self, edge) -> int:
        """Re-add a saved edge (any object with i, j, T_i_j, cov, kind and optionally robust)."""
        kind = str(edge.kind)
        if kind == "prior":
            return self.add_prior(edge.i, edge.T_i_j, edge.cov)
        if kind not in KINDS:
            raise PoseGraphError(f"edge kind {kind!r}: expected one of {', '.join(KINDS)}")
        return self._between(edge.i, edge.j, edge.T_i_j, edge.cov, kind, bool(getattr(edge, "robust", True)))

    def remove_factor(self, handle: int) -> None:
        """Take a factor out of the graph (effective at the next optimise)."""
        if handle not in self._edges:
            raise PoseGraphError(f"no factor with handle {handle}")
        del self._edges[handle]
        del self._factors[handle]
        if handle in self._solver_index:
            self._removed_indices.append(self._solver_index.pop(handle))
        else:
            self._pending.remove(handle)
        self._has_prior = any(e.kind == "prior" for e in self._edges.values())

    # ---------------------------------------------------------------------------- optimising

    def _factor_of(self, tag):
        return self._planar_factors[tag[1]] if isinstance(tag, tuple) else self._factors[tag]

    def _tag_keys(self, tag) -> tuple[int, ...]:
        if isinstance(tag, tuple):
            return (tag[1],)
        e = self._edges[tag]
        return (e.i,) if e.i == e.j else (e.i, e.j)

    def optimise(self, batch: bool = False, max_iterations: int = 20, tol: float = 1e-6) -> float:
        """Bring the estimate up to date; returns the graph's final (robust) error.

        Incremental: the new keyframes that some factor constrains and their factors go into iSAM2,
        then update steps repeat until the error changes by less than ``tol`` (relative).  ``batch``:
        Levenberg-Marquardt over the whole graph from the current estimate, and iSAM2 restarts there;
        also what an incremental call does after an iSAM2 update that raised."""
        if not self._has_prior:
            raise PoseGraphError("the graph has no prior: add_prior on one keyframe to fix the map frame")
        if batch or self._isam_broken:
            return self._optimise_batch(max_iterations)
        # Every pending factor enters with the keyframes it names that iSAM2 does not hold yet.
        ready = list(self._pending)
        constrained = self._in_solver | {k for tag in ready for k in self._tag_keys(tag)}
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for tag in ready:
            graph.add(self._factor_of(tag))
        for k in sorted(constrained - self._in_solver):
            values.insert(self._key(k), self._current_pose(k))
        in_solver_before = set(self._in_solver)
        try:
            result = self._isam.update(graph, values, self._removed_indices)
            for tag, index in zip(ready, result.getNewFactorsIndices()):
                self._solver_index[tag] = int(index)
            self._pending = []
            self._in_solver |= constrained
            self._removed_indices = []
            error = self._isam_error()
            for _ in range(max_iterations):
                self._isam.update()
                new_error = self._isam_error()
                if abs(error - new_error) <= tol * max(error, 1e-12):
                    error = new_error
                    break
                error = new_error
        except _GTSAM_ERRORS as e:       # IndeterminantLinearSystem and friends
            self._isam_broken = True
            self.failed_updates += 1
            self._in_solver = in_solver_before   # the new keyframes keep their initial poses
            if self._factorization != "QR":    # Cholesky's failure: solve it all again, by QR
                self._factorization = "QR"
                return self._optimise_batch(max_iterations)
            raise PoseGraphError(f"pose graph cannot be solved: {_first_line(e)}") from None
        self._set_estimate(self._isam.calculateEstimate())
        return error

    def _set_estimate(self, estimate: gtsam.Values) -> None:
        """Adopt iSAM2's estimate.  iSAM2 drops a keyframe whose last factor was removed: it keeps its
        last pose and waits, like a new keyframe, for a factor to bring it back."""
        for k in list(self._in_solver):
            if not estimate.exists(self._key(k)):
                if self._estimate is not None and self._estimate.exists(self._key(k)):
                    self._initial[k] = self._estimate.atPose3(self._key(k)).matrix()
                self._in_solver.discard(k)
        self._estimate = estimate

    def _isam_error(self) -> float:
        return float(self._isam.getFactorsUnsafe().error(self._isam.calculateEstimate()))

    def _restart_isam(self, graph: gtsam.NonlinearFactorGraph, estimate: gtsam.Values):
        """A new iSAM2 holding ``graph`` at ``estimate``: Cholesky, else QR (kept from then on)."""
        while True:
            self._isam = self._new_isam()
            try:
                result = self._isam.update(graph, estimate)
            except _GTSAM_ERRORS as e:
                self._isam_broken = True
                self.failed_updates += 1
                if self._factorization == "QR":
                    raise PoseGraphError(f"pose graph cannot be solved: {_first_line(e)}") from None
                self._factorization = "QR"
                continue
            self._isam_broken = False
            return result

    def _optimise_batch(self, max_iterations: int) -> float:
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        tags = list(self._factors) + [("planar", k) for k in self._planar_factors]
        used = {k for t in tags for k in self._tag_keys(t)}
        for t in tags:
            graph.add(self._factor_of(t))
        for k in sorted(used):
            values.insert(self._key(k), self._current_pose(k))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(int(max_iterations))
        try:
            estimate = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        except _GTSAM_ERRORS as e:        # (iSAM2 untouched: as healthy, or as broken, as it was)
            raise PoseGraphError(f"pose graph cannot be solved: {_first_line(e)}") from None
        result = self._restart_isam(graph, estimate)
        self._solver_index = {t: int(i) for t, i in zip(tags, result.getNewFactorsIndices())}
        self._pending, self._removed_indices = [], []
        for k in self._in_solver - used:           # lost its last factor: keeps its last pose
            self._initial[k] = self._current_pose(k).matrix()
        self._in_solver = used
        self._estimate = None
        self._set_estimate(self._isam.calculateEstimate())
        return float(graph.error(self._estimate))

    # ------------------------------------------------------------------------------- reading

    def _current_pose(self, kf_id: int) -> gtsam.Pose3:
        if self._estimate is not None and kf_id in self._in_solver and self._estimate.exists(self._key(kf_id)):
            return self._estimate.atPose3(self._key(kf_id))
        return gtsam.Pose3(self._initial[kf_id])

    def __contains__(self, kf_id) -> bool:
        return int(kf_id) in self._initial

    def __len__(self) -> int:
        return len(self._initial)

    def pose(self, kf_id: int) -> np.ndarray:
        """T_map_base of a keyframe: optimised, or its initial pose if no factor has constrained it yet
        (or the optimise that took its first factors in raised)."""
        return self._current_pose(self._require(kf_id, "pose")).matrix()

    def poses(self) -> dict[int, np.ndarray]:
        return {k: self._current_pose(k).matrix() for k in sorted(self._initial)}

    def marginal_covariance(self, kf_id: int, frame: str = "base") -> np.ndarray:
        """6×6 marginal covariance of a keyframe's pose, flyslam order.  ``frame='base'``: the right
        perturbation (errors along/about the keyframe's own axes); ``'map'``: the same errors rotated
        into the map's axes (position error along map x, y, z, rotation about map axes)."""
        kf_id = self._require(kf_id, "marginal_covariance")
        if frame not in ("base", "map"):
            raise PoseGraphError(f"frame {frame!r}: expected 'base' or 'map'")
        if kf_id not in self._in_solver or self._pending or self._isam_broken:
            raise PoseGraphError(f"keyframe {kf_id}: no marginal until optimise() has taken in and solved every "
                                 f"factor and some factor constrains this keyframe")
        try:
            cov = to_gtsam_cov(self._isam.marginalCovariance(self._key(kf_id)))
        except _GTSAM_ERRORS as e:
            raise PoseGraphError(f"marginal covariance of keyframe {kf_id}: {_first_line(e)}") from None
        if frame == "map":
            R = self._current_pose(kf_id).rotation().matrix()
            J = np.zeros((6, 6))
            J[:3, :3] = J[3:, 3:] = R
            cov = J @ cov @ J.T
        return 0.5 * (cov + cov.T)

    def edge(self, handle: int) -> Edge:
        if handle not in self._edges:
            raise PoseGraphError(f"no factor with handle {handle}")
        return self._edges[handle]

    def edges(self) -> dict[int, Edge]:
        """handle -> Edge, every factor the caller added and did not remove (not the planar priors)."""
        return dict(self._edges)

    def residual_chi2(self, handle: int) -> float:
        """eᵀ Σ⁻¹ e of a factor's residual at the current estimate, under its own covariance (no kernel)."""
        edge = self.edge(handle)
        values = gtsam.Values()
        for k in {edge.i, edge.j}:
            values.insert(self._key(k), self._current_pose(k))
        e = np.asarray(self._factors[handle].unwhitenedError(values))[_SWAP]   # flyslam order
        return float(e @ np.linalg.solve(edge.cov, e))

    def report(self, handle: int) -> FactorReport:
        edge = self.edge(handle)
        chi2 = self.residual_chi2(handle)
        weight = float(self._estimator.weight(np.sqrt(chi2))) if edge.robust else 1.0
        return FactorReport(handle, edge, chi2, weight, weight < self.downweight_below)

    def downweighted(self, kind: str | None = None) -> list[FactorReport]:
        """Robust factors the kernel (nearly) ignored at the current estimate, optionally of one kind:
        the rejected loop closures and wheel-slip edges."""
        out = []
        for h, e in self._edges.items():
            if e.robust and (kind is None or e.kind == kind):
                r = self.report(h)
                if r.downweighted:
                    out.append(r)
        return out

    def remove_downweighted(self, kind: str = "registration") -> list[FactorReport]:
        """Remove the down-weighted factors of ``kind`` (their reports are returned); optimise again
        after.  A Cauchy kernel leaves a far outlier a bounded pull (≈ k²/residual, whitened), which
        removal takes away."""
        reports = self.downweighted(kind)
        for r in reports:
            self.remove_factor(r.handle)
        return reports


def _first_line(e: Exception) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__
