"""Progress lines for long command-line work: rewritten in place on a terminal, one line every
``every`` steps when stderr is a file or a pipe (logs stay readable)."""
from __future__ import annotations

import sys
import time


class Progress:
    def __init__(self, label: str, every: int = 25):
        self.label, self.every = label, every
        self.tty = sys.stderr.isatty()
        self.t0 = time.monotonic()
        self._shown = False

    def update(self, count: int, text: str = "") -> None:
        line = f"[{self.label}] {count} {text} ({time.monotonic() - self.t0:.0f} s)"
        if self.tty:
            print(f"\r{line[:110]:<110}", end="", file=sys.stderr, flush=True)
            self._shown = True
        elif count % self.every == 0:
            print(line, file=sys.stderr, flush=True)

    def done(self) -> None:
        if self._shown:
            print(file=sys.stderr)
