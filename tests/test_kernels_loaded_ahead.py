"""The evolver and the localiser load their numba kernels before their first input
(common.fly.core.warm_up, common.slam.core.warm_up): a live start's first frame and first fix, mono or
colour at any size, then load none, instead of paying for them while the camera moves on."""
from __future__ import annotations

import json
import os
import subprocess
import sys

from tests.helpers import ROOT

PRELUDE = """
import json
import numpy as np
from common import messages as m
from common.camera import StereoCalibration
from common.fly import EvolverConfig
from common.fly.core import EvolverCore
from common.images import make_frame
from common.warmup import kernel_modules, kernels

found = kernels(kernel_modules())
loaded = lambda: {name: len(d.signatures) for name, d in found.items() if d.signatures}
rng = np.random.default_rng(0)

def frames(shape, encoding, n):
    core = EvolverCore(EvolverConfig(), settle=3)
    cal = StereoCalibration.ideal(width=shape[1], height=shape[0], baseline=0.5)
    core.on_calibration(m.calibration_to_msg(cal))
    img = rng.integers(0, 255, shape, dtype=np.uint8)
    for k in range(n):
        shifted = np.roll(img, -k, axis=1)
        result = core.on_frame(make_frame(shifted, np.roll(shifted, -8, axis=1), k + 1, (k + 1) * 10**8,
                                          encoding=encoding))
        assert result.population is not None, result.reason
        yield cal, core, result.population
"""

EVOLVER = PRELUDE + """
from common.fly.core import warm_up
before = loaded()
warm_up(EvolverConfig())
after_warm_up = loaded()
for shape, encoding in (((376, 620), "png"), ((240, 320, 3), "jpeg")):
    list(frames(shape, encoding, 1))
print(json.dumps({"before": before, "after_warm_up": after_warm_up, "after": loaded()}))
"""

LOCALISER = PRELUDE + """
from common.slam import LocaliserConfig
from common.slam.core import LocaliserCore, warm_up
pops = list(frames((240, 320), "png", 4))          # the evolver's kernels, loaded before counting
before = loaded()
warm_up(LocaliserConfig())
after_warm_up = loaded()
core = LocaliserCore(LocaliserConfig(odometry="visual", min_generations=1))
core.on_calibration(m.calibration_to_msg(pops[0][0]))
statuses = [core.on_population(pop) for _, _, pop in pops]
assert any(s.estimate is not None and s.estimate.status == "ok" for s in statuses), statuses
print(json.dumps({"before": before, "after_warm_up": after_warm_up, "after": loaded()}))
"""


def run(script: str) -> dict:
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def new_kernels(got: dict) -> dict:
    return {k: v for k, v in got["after"].items() if got["after_warm_up"].get(k) != v}


def test_the_first_frames_load_no_kernel_after_the_evolvers_warm_up():
    got = run(EVOLVER)
    assert not got["before"]                                   # a fresh process has none loaded
    assert len(got["after_warm_up"]) >= 5
    assert not new_kernels(got), f"kernels the first frames still had to load: {new_kernels(got)}"


def test_the_first_fixes_load_no_kernel_after_the_localisers_warm_up():
    got = run(LOCALISER)
    assert len(got["after_warm_up"]) > len(got["before"])      # it loaded some of its own
    assert not new_kernels(got), f"kernels the first fixes still had to load: {new_kernels(got)}"



def test_a_cold_numba_cache_is_told_apart_so_the_evolver_does_not_compile_before_joining_the_bus(tmp_path):
    """services/evolver.py loads its kernels before it announces itself only when that is a load: a
    compile takes seconds, and the supervisor takes a process without a liveliness token for hung."""
    check = ("from common.fly import fitness, operators\nfrom common.numba_cache import on_disk\n"
             "print(on_disk([fitness._fitness_kernel_serial, operators.plan_batch]))")
    compile_them = "from common.fly import EvolverConfig\nfrom common.fly.core import warm_up\nwarm_up(EvolverConfig())"
    answers = []
    for script in (check, compile_them, check):     # in an empty cache: cold; the warm-up compiles and saves
        done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=300,
                              env=dict(os.environ, PYTHONPATH=str(ROOT), NUMBA_CACHE_DIR=str(tmp_path)))
        assert done.returncode == 0, done.stderr
        answers.append(done.stdout.strip())
    assert answers == ["False", "", "True"]
