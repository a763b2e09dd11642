"""Cached simulated recordings follow the simulator's code: a stale recording is never reused."""
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from common.recording import RecordingReader
from common.sim import offline

ROOT = Path(__file__).resolve().parent.parent


def test_a_simulator_change_makes_the_cached_recording_again_and_drops_the_old_one(tmp_path, monkeypatch):
    source = tmp_path / "render.py"
    source.write_text("WALL_TEXTURE = 1\n")
    made = []

    def simulate(scenario, out, seed=0, progress=None, **options):
        made.append(Path(out))
        Path(out).write_bytes(b"recording")

    cache = tmp_path / "cache"
    monkeypatch.setattr(offline, "CACHE_DIR", cache)
    monkeypatch.setattr(offline, "SIMULATOR_SOURCES", (source,))
    monkeypatch.setattr(offline, "simulate_to_recording", simulate)
    first = offline.cached_recording("loop", seed=0)
    other_options = offline.cached_recording("loop", seed=0, fps=30.0)
    assert offline.cached_recording("loop", seed=0) == first and len(made) == 2     # reused as is
    source.write_text("WALL_TEXTURE = 2\n")
    second = offline.cached_recording("loop", seed=0)
    assert second != first and len(made) == 3                                         # made again
    assert not first.exists() and other_options.exists()   # the stale one goes, other options' stay


def test_the_digest_covers_every_module_the_simulator_imports():
    listed = {f.relative_to(ROOT).as_posix() for f in offline.SIMULATOR_SOURCES}
    out = subprocess.run([sys.executable, "-c", "import sys, common.sim.offline; print('\\n'.join("
                          "m.__file__ for n, m in sys.modules.items() if n.startswith('common') and "
                          "getattr(m, '__file__', None)))"], cwd=ROOT, capture_output=True, text=True, check=True)
    imported = {Path(f).resolve().relative_to(ROOT).as_posix() for f in out.stdout.split()}
    unlisted = imported - listed - {"common/__init__.py", "common/numba_cache.py", "common/trajectory.py"}
    assert not unlisted, f"the simulator imports {sorted(unlisted)}: add them to SIMULATOR_SOURCES"
    assert all(f.is_file() for f in offline.SIMULATOR_SOURCES)


def test_two_writers_of_one_recording_at_once_both_finish_with_a_whole_file(tmp_path):
    out = tmp_path / "corridor.mcap"
    start, errors, summaries = threading.Barrier(2), [], []

    def simulate():
        start.wait()
        try:
            summaries.append(offline.simulate_to_recording("corridor", out, seconds=0.3, width=160, height=120))
        except Exception as e:  # noqa: BLE001 - the test reports it
            errors.append(e)

    threads = [threading.Thread(target=simulate) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len(summaries) == 2
    frames = sum(rec.key.endswith("stereo/frame") for rec in RecordingReader(out).messages())
    assert frames == summaries[0]["frames"] > 0
    assert not list(tmp_path.glob("*.partial"))


def test_an_interrupted_simulation_leaves_neither_a_recording_nor_a_partial_file(tmp_path):
    out = tmp_path / "corridor.mcap"

    def interrupt(seconds, frames):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        offline.simulate_to_recording("corridor", out, seconds=0.3, width=160, height=120, progress=interrupt)
    assert list(tmp_path.iterdir()) == []
