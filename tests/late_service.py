"""A stand-in service for the supervisor's tests: it writes the time it started to ``<run>/<name>.started``,
joins the bus (its liveliness token appears) only ``--delay`` seconds later, as the evolver does after
loading its kernels, writes that time to ``<run>/<name>.up`` and idles until stopped."""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from services.base import run_service, service_parser


def main(argv: list[str] | None = None) -> int:
    parser = service_parser("late", __doc__.splitlines()[0])
    parser.add_argument("--name", required=True)
    parser.add_argument("--delay", type=float, default=0.0)
    args = parser.parse_args(argv)
    run = Path(os.environ["FLYSLAM_RUN_DIR"])
    (run / f"{args.name}.started").write_text(repr(time.time()))

    def idle(node, _args):
        (run / f"{args.name}.up").write_text(repr(time.time()))
        while node.sleep(0.1):
            pass

    return run_service(args.name, parser, idle, argv, prepare=lambda _args: time.sleep(args.delay))


if __name__ == "__main__":
    sys.exit(main())
