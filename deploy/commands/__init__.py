"""Implementations of `flyslam` subcommands that are tools rather than long-running services."""
