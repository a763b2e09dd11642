"""flyslam common library: pure algorithms (no I/O), message schemas and codec, the Zenoh bus layer
and recording formats. Services in `services/` are thin wrappers around this package."""
