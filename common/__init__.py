"""flyslam common library: pure algorithms (no I/O), message schemas and codec, the Zenoh bus layer
and recording formats. Services in `services/` are thin wrappers around this package."""

from common.numba_cache import configure as _configure_numba_cache

_configure_numba_cache()   # before any kernel module is imported: where numba keeps compiled kernels
