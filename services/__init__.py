"""flyslam services: one thin module per process (subscribe, call `common`, publish)."""
