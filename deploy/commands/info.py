"""`flyslam info FILE`: summary of a recording — channels, message counts, duration, rates, metadata.

FILE is an MCAP file (its numbered segments, written by a restarted recorder, are included) or a run
folder holding one recording.

Exit status 0 for a sound file, 3 when the file is truncated or corrupt (the summary then covers the
readable part and names the problem), 2 when it cannot be opened at all.
"""
from __future__ import annotations

import argparse
import sys

from common.recording import RecordingError, RecordingReader


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="flyslam info", description=__doc__.splitlines()[0])
    p.add_argument("recordings", nargs="+", help="MCAP files or run folders")
    args = p.parse_args(argv)
    status = 0
    for path in args.recordings:
        try:
            info = RecordingReader(path).info()
        except RecordingError as e:
            print(f"flyslam info: {e}", file=sys.stderr)
            status = max(status, 2)
            continue
        print(info.format())
        if info.error:
            status = max(status, 3)
    return status


if __name__ == "__main__":
    sys.exit(main())
