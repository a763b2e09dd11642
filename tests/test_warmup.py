"""The numba kernels compile at install time (python -m common.warmup), not during a run."""
from pathlib import Path

from common import numba_cache, warmup


def test_warmup_reaches_every_kernel_a_run_uses():
    # A kernel added to common/ without a warm-up path would compile in the first run of every install.
    assert warmup.main([]) == 0
    assert len(warmup.kernels(warmup.kernel_modules())) > 50


def test_parallel_and_serial_fitness_kernels_keep_separate_cache_entries():
    # numba keys its disk cache by name, signature and bytecode, not by parallel=True/False: sharing one
    # entry, whichever variant a machine compiled first was loaded for both.
    from common.fly import fitness
    par, ser = fitness._fitness_kernel_parallel._cache, fitness._fitness_kernel_serial._cache
    assert par._cache_file._index_name != ser._cache_file._index_name


def test_cache_moves_to_the_user_cache_when_the_sources_are_read_only(monkeypatch, tmp_path):
    from numba.core import config
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(numba_cache, "PACKAGE_DIR", Path("/proc/flyslam-read-only"))  # mkdir fails, even as root
    try:
        chosen = numba_cache.configure()
        assert chosen == str(tmp_path / "flyslam" / "numba")
        assert config.CACHE_DIR == chosen
    finally:
        monkeypatch.undo()
        config.reload_config()
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "mine"))
    assert numba_cache.configure() == str(tmp_path / "mine"), "an explicit NUMBA_CACHE_DIR wins"
