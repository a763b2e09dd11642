"""StereoModel: how the flies were measured, and the registration that weights them by it.

    register_planar(A, B, stereo=StereoModel(rig))   # what the SLAM localiser runs on deep scenes

_register_stereo turns the model into per-fly weights (depth, footprint, optional co-visibility) and
calls the registration driver once per pass, each pass's estimate the next one's prior.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import StereoCalibration
from .pseudo_distance import as_population, as_weights
from .weights import covisible_masks, depth_weights, footprint_weights


@dataclass
class StereoModel:
    """How the flies were measured, for registration on deep (outdoor) scenes: what the SLAM service
    should pass.  The defaults are the variant that won on the deep street scene of
    bench/registration_variants.py (local objective, footprint × depth weights, B thinned); the
    measured variants and why each term helps are in docs/design/registration.md.

    calib: the rig (both populations were seen through it).  depth_range: the depths flies can have
    (metres), for co-visibility.  frame: the populations' frame for 6-DoF ("optical" or "body"; the
    planar modes use their plane's frame).  depth_weighting: 1/(1 + (σ_z/sigma_ref)²).
    footprint_weighting: (z/10 m)².  covisibility: keep only flies the other camera could see under
    the current estimate, re-derived for each of `passes` registrations (off: it did not help on the
    street and costs a pass).  objective: "local" (LocalCorrelationField with cut-off `local_radius`)
    or "delta" (the paper's δ, weighted).  thin_b: Russian roulette on B by weight (unbiased field,
    fewer neighbours).  lattice_step: coarse-lattice spacing in metres of fly motion (see
    lattice._lattice_counts; None: the full `lattice` counts); 0.5 m is half the coarse kernel's
    2 × local_radius cut-off, below which candidates repeat each other's basin.
    """
    calib: StereoCalibration
    depth_range: tuple = (0.0, np.inf)
    disparity_sigma: float = 0.4
    sigma_ref: float = 0.25
    depth_weighting: bool = True
    footprint_weighting: bool = True
    covisibility: bool = False
    margin: float = 0.03
    passes: int = 1
    frame: str = "optical"
    objective: str = "local"
    local_radius: float = 0.5
    thin_b: bool = True
    lattice_step: float | None = 0.5


def _register_stereo(mode, A, B, stereo: StereoModel, prior, window, weights_a, weights_b, args, register):
    """Registration with depth-uncertainty weights and co-visibility masks, iterated `passes` times.

    register: the registration driver (register._register), called once per pass with the weights.
    """
    frame = {"optical": "optical", "body": "body"}.get(mode, stereo.frame)
    A = as_population(A, "A", allow_empty=True)
    B = as_population(B, "B", allow_empty=True)
    wa = as_weights(weights_a, len(A), "weights_a").copy()
    wb = as_weights(weights_b, len(B), "weights_b").copy()
    if stereo.depth_weighting:
        wa *= depth_weights(A, stereo.calib, stereo.disparity_sigma, stereo.sigma_ref, frame)
        wb *= depth_weights(B, stereo.calib, stereo.disparity_sigma, stereo.sigma_ref, frame)
    if stereo.footprint_weighting:
        wa *= footprint_weights(A, stereo.calib, frame)
        wb *= footprint_weights(B, stereo.calib, frame)
    if stereo.thin_b and len(B):
        # Russian roulette on B: keep a fly with probability min(1, w / median w) and divide its
        # weight by that probability.  The field is unchanged in expectation, but the dense, light
        # near-camera flies (most of the neighbour work) are mostly gone.
        rng = np.random.default_rng(args["rest"][7])
        ref = float(np.median(wb[wb > 0])) if np.any(wb > 0) else 1.0
        p_keep = np.minimum(1.0, wb / ref)
        keep = rng.random(len(B)) < p_keep
        B, wb = B[keep], wb[keep] / p_keep[keep]
    T = np.eye(4) if prior is None else np.asarray(prior, dtype=float)
    res = None
    for _ in range(max(1, int(stereo.passes))):
        wa_p, wb_p = wa, wb
        if stereo.covisibility:
            ma, mb = covisible_masks(A, B, T, stereo.calib, stereo.depth_range, stereo.margin, frame)
            wa_p, wb_p = wa * ma, wb * mb
        rest = args["rest"][:-2] + (stereo.objective, stereo.local_radius)
        step = stereo.lattice_step if args["lattice_step"] is None else args["lattice_step"]
        res = register(mode, A, B, args["eps"], T, window, wa_p, wb_p, *rest, lattice_step=step,
                        curvature=args.get("curvature", True))
        if not res.ok:
            return res
        T = res.T
    return res
