"""flyslam deployment: the supervisor, launch files, Zenoh configurations and the `flyslam` command."""
