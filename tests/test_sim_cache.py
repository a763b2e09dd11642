"""Cached simulated recordings follow the simulator's code: a stale recording is never reused."""
from pathlib import Path

from common.sim import offline


def test_a_simulator_change_makes_the_cached_recording_again(tmp_path, monkeypatch):
    source = tmp_path / "render.py"
    source.write_text("WALL_TEXTURE = 1\n")
    made = []

    def simulate(scenario, out, seed=0, progress=None, **options):
        made.append(Path(out))
        Path(out).write_bytes(b"recording")

    monkeypatch.setattr(offline, "CACHE_DIR", tmp_path / "cache")
    monkeypatch.setattr(offline, "SIMULATOR_SOURCES", (source,))
    monkeypatch.setattr(offline, "simulate_to_recording", simulate)
    first = offline.cached_recording("loop", seed=0)
    assert offline.cached_recording("loop", seed=0) == first and len(made) == 1     # reused as is
    source.write_text("WALL_TEXTURE = 2\n")
    second = offline.cached_recording("loop", seed=0)
    assert second != first and len(made) == 2                                         # made again
    assert offline.cached_recording("loop", seed=1) not in (first, second)


def test_the_digest_covers_the_simulator_package():
    names = {f.name for f in offline.SIMULATOR_SOURCES}
    assert {"simulator.py", "render.py", "scenario.py", "images.py"} <= names
    assert all(f.is_file() for f in offline.SIMULATOR_SOURCES)
