"""Compile (or load from numba's cache) every numba kernel in ``common``: ``python -m common.warmup``.

deploy/setup.sh runs it once per install, so no run pays for compilation.  The kernels are driven through
the same public calls the services make (a few frames of a small simulated corridor: render, sonar, the
evolver with its sonar term, the localiser, the planner), so they compile for the argument types a run
uses.  Afterwards every kernel of the scanned modules must be ``cache=True`` and hold a compiled signature
or be called by another kernel (compiled with it; inline-only helpers excepted); a kernel left out is
named and the exit status is 1.
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
import time
from pathlib import Path

import numpy as np

import common
from common import numba_cache

_SKIP = ("common.warmup",)
# Defined but called by nothing in the repository (not even by another kernel): nothing to warm.
UNUSED = ("common.planning.multigrid.level_scales",)


def kernel_modules() -> list[str]:
    """Dotted names of the modules under common/ whose source jit-compiles something."""
    root = Path(common.__file__).resolve().parent
    names = []
    for info in pkgutil.walk_packages([str(root)], prefix="common."):
        if info.ispkg or info.name in _SKIP:
            continue
        path = root.joinpath(*info.name.split(".")[1:]).with_suffix(".py")
        if path.is_file() and "njit(" in path.read_text(encoding="utf-8"):
            names.append(info.name)
    return sorted(names)


def kernels(modules: list[str]) -> dict[str, object]:
    """'module.name' → numba dispatcher, for every dispatcher defined in ``modules`` (inline-only excepted)."""
    from numba.core.registry import CPUDispatcher
    found = {}
    for name in modules:
        mod = importlib.import_module(name)
        for attr, obj in vars(mod).items():
            if isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == name \
                    and obj.targetoptions.get("inline") != "always":
                found[f"{name}.{attr}"] = obj
    return found


def uncached(found: dict[str, object]) -> list[str]:
    """Kernels without ``cache=True``: they would compile in every process."""
    from numba.core.caching import FunctionCache
    return sorted(k for k, d in found.items() if not isinstance(d._cache, FunctionCache))


def callees(found: dict[str, object]) -> set[str]:
    """Kernels named inside another kernel's body: numba compiles them with their caller (and loads
    them from the cache with it, without listing their signatures on their own dispatcher)."""
    names = set()
    for d in found.values():
        for n in d.py_func.__code__.co_names:
            callee = getattr(d.py_func.__globals__.get(n), "py_func", None)   # imported kernels too
            if callee is not None:
                names.add(f"{callee.__module__}.{callee.__name__}")
    return names


def _exercise() -> None:
    """A few frames of the pipeline's algorithms, in-process, on a small simulated corridor."""
    from common.fly import EvolverConfig, FlyEvolver
    from common.fly.fitness import image_fitness
    from common.fusion.sonar_term import SonarTerm, SonarTermConfig
    from common.geometry import invert, transform_points
    from common.planning import HarmonicPlanner, PlannerConfig, SensorView
    from common.planning import harmonic as hk
    from common.registration import (LocalCorrelationField, PseudoDistanceField, field_exact, register_6dof,
                                     register_planar)
    from common.sim import CameraDue, SonarReading, Simulator, load_scenario, scenario_path
    from common.sim.bus_messages import sonar_message
    from common.sim.render import noise_table
    from common.slam.localiser import FlyLocaliser

    sim = Simulator(load_scenario(scenario_path("corridor")), seed=0, width=160, height=120)
    cal = sim.calibration
    ev = FlyEvolver(cal, EvolverConfig(population=1500), seed=0)
    term = SonarTerm(SonarTermConfig(reward_gain=1.0))
    ev.add_fitness_term("sonar", term, 0.5)
    loc = FlyLocaliser(cal.T_base_camera)
    planner = HarmonicPlanner(PlannerConfig(resolution=0.1, size_m=(12.0, 12.0), origin=(-6.0, -6.0)))
    planner.set_target(4.0, 0.0, 0.4)
    sim.set_command(0.3, 0.05)
    frames, T_prev = 0, None
    while frames < 4 and not sim.finished:
        for e in sim.advance(0.05):
            if isinstance(e, SonarReading):
                scan = sonar_message(e, sim.time_ns)
                term.update(scan, cal.T_base_camera)
            elif isinstance(e, CameraDue):
                img = sim.render(sim.time_ns)
                if T_prev is not None:
                    ev.move_flies(invert(img.T_map_base @ cal.T_base_camera) @ T_prev @ cal.T_base_camera,
                                  rescore=False)
                T_prev = img.T_map_base
                ev.set_images(img.left, img.right)
                ev.step(3)
                loc.update(sim.time_ns, np.array(ev.positions), np.array(ev.fitness), img.T_map_base,
                           generation=ev.generation)
                pts = transform_points(img.T_map_base @ cal.T_base_camera, ev.positions)
                x, y, yaw = (float(v) for v in sim.pose)
                planner.update_flies(pts, np.array(ev.fitness), sim.time_ns,
                                     view=SensorView(x, y, yaw, 0.6, 5.0, 0.3))
                planner.solve()
                planner.command((x, y, yaw))
                planner.path_from(x, y)
                frames += 1
    # Photometric tracking (the localiser's with images): float64 flies, float32 pyramids.
    from common.registration.photometric import align_flies, coarse_candidates, pyramid
    grey = img.left if img.left.ndim == 2 else img.left.mean(axis=2).astype(np.uint8)
    flies = np.array(ev.positions, np.float64)
    align_flies(flies, np.ones(len(flies)), pyramid(grey, 2), pyramid(grey, 2), cal.K_rectified, min_flies=1)
    coarse_candidates(flies, np.ones(len(flies)), pyramid(grey, 2), pyramid(grey, 2), cal.K_rectified)
    # Both fitness kernels (the evolver picks one by measured cost), on writable and read-only flies.
    for parallel in (True, False):
        image_fitness(ev.frame, cal, ev.positions, parallel=parallel)
        image_fitness(ev.frame, cal, np.array(ev.positions), parallel=parallel)
    ev_gen = FlyEvolver(cal, EvolverConfig(population=500, mode="generational"), seed=1)
    ev_gen.set_images(img.left, img.right)
    ev_gen.step(2)
    # Registration entry points beyond the localiser's own.
    A = np.array(ev.positions, np.float64)[np.isfinite(ev.fitness)][:400]
    register_planar(A, A + [0.02, 0.0, 0.01])
    register_planar(A, A + [0.02, 0.0, 0.01], objective="local")
    register_6dof(A, A + [0.02, 0.0, 0.01])
    field_exact(A, A, 0.1)
    field_exact(A, A, 0.1, with_grad=True)
    for deposit in ("tsc", "cic"):
        for parallel_min in (1, 10 ** 9):
            PseudoDistanceField(A, 0.1, deposit=deposit, parallel_min=parallel_min).field(A[:50], with_grad=True)
    local = LocalCorrelationField(A, 0.1, 0.5)
    local.field(A[:50], with_grad=True)
    local.correlation(A)
    # The simulator's motion-blur path (one view at a time) and the planner's bench-side measures.
    r = sim.renderer
    rad, _ = r.radiance(T_prev @ cal.T_base_camera)
    r.expose(rad, 1.0, 1.0, 0.0, r.vignette(0.2), noise_table(0), np.random.default_rng(0), 0.5, 0.01)
    psi = np.full(planner._state.shape, -np.inf)
    psi[1:-1, 1:-1] = planner.log_phi
    hk.usable_fraction(psi, planner._state)
    for dtype in (np.float64, np.float32):
        hk.plain_potential(planner._state, dtype, max_sweeps=2)
    planner._solver.residual()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.parse_args(argv)
    t0 = time.perf_counter()
    found = kernels(kernel_modules())
    t_import = time.perf_counter() - t0
    _exercise()
    inner = callees(found)
    missing = sorted(k for k, d in found.items() if not d.signatures and k not in inner and k not in UNUSED)
    compiled = sum(sum(d.stats.cache_misses.values()) for d in found.values())
    loaded = sum(sum(d.stats.cache_hits.values()) for d in found.values())
    where = numba_cache.configure() or "next to the sources (__pycache__)"
    print(f"[warmup] {len(found)} numba kernels ready in {time.perf_counter() - t0:.1f} s "
          f"(imports {t_import:.1f} s): {compiled} signatures compiled, {loaded} loaded from the cache in {where}",
          file=sys.stderr)
    status = 0
    if missing:
        print(f"[warmup] not exercised, will compile in a run: {', '.join(missing)}", file=sys.stderr)
        status = 1
    if uncached(found):
        print(f"[warmup] not cache=True, will compile in every run: {', '.join(uncached(found))}", file=sys.stderr)
        status = 1
    return status


if __name__ == "__main__":
    sys.exit(main())
