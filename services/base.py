"""What every service process shares: argument parsing with the bus flags, logging, the Node."""
from __future__ import annotations

import argparse
import logging
import os
import sys
from contextlib import contextmanager
from typing import Callable

from common.allocator import retain_freed_memory
from common.bus import Node, add_bus_arguments, bus_options, setup_logging
from common.config_args import config_from_args


def load_kernels_ahead(log: logging.Logger, warm_up: Callable[[], float], first_use: str,
                       probes: list | None = None) -> None:
    """Run a core's ``warm_up`` (numba loads its kernels from the cache) before the service takes its
    inputs, so ``first_use`` ("the first frame") pays for none.  With ``probes`` (one kernel per kernel
    module: numba's index is per source file), skipped when the cache lacks them: they would compile
    instead, seconds without a liveliness token, which the supervisor takes for a hung process.  A
    failure only loses the head start: logged, never raised."""
    if probes is not None:
        from common.numba_cache import on_disk
        if not on_disk(probes):
            log.warning("numba's cache lacks the %s's kernels: %s will compile them "
                        "(`python -m common.warmup` compiles every kernel once)", log.name.rsplit(".", 1)[-1],
                        first_use)
            return
    try:
        log.info("kernels loaded in %.2f s", warm_up())
    except Exception as e:  # noqa: BLE001 - only a head start: the first use loads them instead
        log.warning("loading the kernels ahead failed (%s: %s); %s will", type(e).__name__, e, first_use)


def service_parser(name: str, description: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=f"flyslam {name}", description=description,
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    add_bus_arguments(parser)
    return parser


def config_or_exit(cls, args: argparse.Namespace, only=None, rename=None, **extra):
    """The dataclass ``cls`` the flags describe; an invalid combination ends the process with one line."""
    try:
        return config_from_args(cls, args, only, rename, **extra)
    except ValueError as e:
        raise SystemExit(f"flyslam: {e}") from None


@contextmanager
def survive(node: Node, what: str, log: logging.Logger, on: str = ""):
    """Run one message's (or one cycle's) processing so that an exception costs that message only: it is
    counted as ``step_errors`` and ``<what>_errors`` and logged (the first 5, then every 100th; ``on``
    names the stream in the log), and the service's loop carries on. Only ``Exception``: SystemExit and
    KeyboardInterrupt still end the process."""
    try:
        yield
    except Exception as e:  # noqa: BLE001 - a service's loop must survive any single message
        node.counters.add("step_errors")
        node.counters.add(f"{what}_errors")
        n = node.counters.get(f"{what}_errors")
        if n <= 5 or n % 100 == 0:
            log.warning("%s failed%s: %s: %s (%d so far)", what, f" on {on}" if on else "", type(e).__name__,
                        str(e).splitlines()[0] if str(e) else "", n)


def one_opencv_thread() -> None:
    """OpenCV calls run on the calling thread (``OPENCV_FOR_THREADS_NUM`` overrides).  The services share
    the machine's cores as separate processes; OpenCV's own pool only adds wake-ups and spinning (more
    CPU for the same wall time)."""
    value = os.environ.setdefault("OPENCV_FOR_THREADS_NUM", "1")   # read when cv2 loads ...
    if not value.isdigit() or int(value) < 1:
        raise SystemExit(f"flyslam: OPENCV_FOR_THREADS_NUM must be a whole number of threads ≥ 1, got {value!r}")
    if "cv2" in sys.modules:                                        # ... or set now when it is loaded
        sys.modules["cv2"].setNumThreads(int(value))


def run_service(name: str, parser: argparse.ArgumentParser, body: Callable[[Node, argparse.Namespace], int | None],
                argv: list[str] | None = None,
                prepare: Callable[[argparse.Namespace], None] | None = None) -> int:
    """Parse arguments, open the service's Node and run ``body(node, args)`` until it returns.

    SIGINT/SIGTERM set ``node.stopping``; bodies loop ``while not node.stopping`` and return to exit
    cleanly (files closed, liveliness token withdrawn).  ``prepare(args)`` runs before the node joins
    the bus (loading kernels): a service announces itself when it can take its inputs.
    """
    args = parser.parse_args(argv)
    retain_freed_memory()   # per-frame arrays reused, not page-faulted in again (common.allocator)
    one_opencv_thread()
    setup_logging(name, getattr(args, "log_level", None))
    if prepare is not None:
        prepare(args)
    with Node(name, bus_options(args)) as node:
        return int(body(node, args) or 0)
