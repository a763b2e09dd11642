"""Trajectory text formats used by the evaluation tools: TUM and KITTI (as read by `evo`).

TUM: one pose per line, ``timestamp tx ty tz qx qy qz qw`` (timestamp in seconds, quaternion xyzw),
lines starting with ``#`` are comments.  KITTI: one pose per line, the first three rows of the 4×4
matrix, row-major (12 numbers), no timestamps.

Stamps are int64 nanoseconds in memory; TUM text carries them as decimal seconds with 9 fractional
digits and they are parsed back exactly (no float round trip), so ``read(write(x)) == x`` for stamps.
Poses are (N, 4, 4) float64 arrays ``T_world_body``.
"""
from __future__ import annotations

import os
import time
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from common.geometry import matrix_from_quat, quat_from_matrix


class TrajectoryFormatError(ValueError):
    """A trajectory file or array that does not follow its format; the message names where."""


# ----------------------------------------------------------------------------------------- checks
def _check_poses(stamps_ns, poses) -> tuple[np.ndarray | None, np.ndarray]:
    P = np.asarray(poses, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (4, 4):
        raise TrajectoryFormatError(f"poses must be an (N, 4, 4) array, got shape {P.shape}")
    if not np.all(np.isfinite(P)):
        raise TrajectoryFormatError("poses contain NaN or inf")
    if stamps_ns is None:
        return None, P
    S = np.asarray(stamps_ns)
    if S.ndim != 1 or S.shape[0] != P.shape[0]:
        raise TrajectoryFormatError(
            f"stamps_ns must be a 1-D array with one stamp per pose ({P.shape[0]}), got shape {S.shape}")
    if not np.issubdtype(S.dtype, np.integer):
        raise TrajectoryFormatError(f"stamps_ns must be integer nanoseconds, got dtype {S.dtype}")
    return S.astype(np.int64), P


def _stamp_text(ns: int) -> str:
    ns = int(ns)
    sign = "-" if ns < 0 else ""
    s, frac = divmod(abs(ns), 1_000_000_000)
    return f"{sign}{s}.{frac:09d}"


def _parse_stamp(text: str, where: str) -> int:
    try:
        d = Decimal(text)
    except InvalidOperation:
        raise TrajectoryFormatError(f"{where}: timestamp {text!r} is not a number") from None
    if not d.is_finite():
        raise TrajectoryFormatError(f"{where}: timestamp {text!r} is not finite")
    return int((d * 1_000_000_000).to_integral_value())


def _lines(text: str):
    for i, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        yield i, line


def _floats(fields, where: str) -> np.ndarray:
    try:
        vals = np.array([float(f) for f in fields], dtype=np.float64)
    except ValueError:
        raise TrajectoryFormatError(f"{where}: non-numeric value in {' '.join(fields)!r}") from None
    if not np.all(np.isfinite(vals)):
        raise TrajectoryFormatError(f"{where}: NaN or inf value")
    return vals


def _split(line: str) -> list[str]:
    # evo accepts space- or comma-separated rows; so do we.
    return line.replace(",", " ").split()


# -------------------------------------------------------------------------------------------- TUM
def format_tum(stamps_ns, poses) -> str:
    """TUM text of a trajectory: one ``t tx ty tz qx qy qz qw`` line per pose."""
    S, P = _check_poses(stamps_ns, poses)
    out = []
    for s, T in zip(S, P):
        q = quat_from_matrix(T[:3, :3])
        t = T[:3, 3]
        out.append(f"{_stamp_text(s)} {t[0]:.9f} {t[1]:.9f} {t[2]:.9f} "
                   f"{q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")
    return "\n".join(out) + ("\n" if out else "")


def parse_tum(text: str, source: str = "<text>") -> tuple[np.ndarray, np.ndarray]:
    """(stamps_ns (N,) int64, poses (N, 4, 4)) from TUM text. ``source`` names the input in errors."""
    stamps, poses = [], []
    for lineno, line in _lines(text):
        where = f"{source}:{lineno}"
        fields = _split(line)
        if len(fields) != 8:
            raise TrajectoryFormatError(
                f"{where}: a TUM row has 8 columns (timestamp tx ty tz qx qy qz qw), got {len(fields)}")
        stamps.append(_parse_stamp(fields[0], where))
        v = _floats(fields[1:], where)
        qn = np.linalg.norm(v[3:])
        if qn < 1e-9:
            raise TrajectoryFormatError(f"{where}: quaternion has zero norm")
        T = np.eye(4)
        T[:3, :3] = matrix_from_quat(v[3:])
        T[:3, 3] = v[:3]
        poses.append(T)
    if not poses:
        return np.zeros(0, np.int64), np.zeros((0, 4, 4))
    return np.array(stamps, dtype=np.int64), np.stack(poses)


def _write_atomically(path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file and a rename: a reader (or a process killed
    mid-write) sees the old file or the new one, never half of one."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_tum(path, stamps_ns, poses) -> None:
    _write_atomically(path, format_tum(stamps_ns, poses))


class TumFile:
    """A trajectory kept on disk as it grows, for a process that may be killed at any moment.

    :meth:`append` adds a pose; at most every ``period_s`` (and on :meth:`flush`) the whole file is
    rewritten atomically, formatting only the poses added since the last write. The file always holds
    a complete TUM trajectory, at most ``period_s`` behind."""

    def __init__(self, path, period_s: float = 1.0):
        self.path, self.period_s = Path(path), period_s
        self._text: list[str] = []
        self._stamps: list[int] = []
        self._poses: list[np.ndarray] = []
        self._count = 0
        self._written_at = time.monotonic()

    def __len__(self) -> int:
        return self._count

    def append(self, stamp_ns: int, T_world_body: np.ndarray) -> None:
        self._stamps.append(int(stamp_ns))
        self._poses.append(T_world_body)
        self._count += 1
        if time.monotonic() - self._written_at >= self.period_s:
            self.flush()

    def flush(self) -> None:
        if self._stamps:
            self._text.append(format_tum(np.array(self._stamps, np.int64), np.array(self._poses)))
            self._stamps, self._poses = [], []
        _write_atomically(self.path, "".join(self._text))
        self._written_at = time.monotonic()


def read_tum(path) -> tuple[np.ndarray, np.ndarray]:
    p = Path(path)
    return parse_tum(p.read_text(), source=str(p))


# ------------------------------------------------------------------------------------------ KITTI
def format_kitti(poses) -> str:
    """KITTI text of a trajectory: the top 3×4 of each pose, row-major, 12 numbers per line."""
    _, P = _check_poses(None, poses)
    return "".join(" ".join(f"{x:.9e}" for x in T[:3, :4].ravel()) + "\n" for T in P)


def parse_kitti(text: str, source: str = "<text>") -> np.ndarray:
    """(N, 4, 4) poses from KITTI text."""
    poses = []
    for lineno, line in _lines(text):
        where = f"{source}:{lineno}"
        fields = _split(line)
        if len(fields) != 12:
            raise TrajectoryFormatError(
                f"{where}: a KITTI row has 12 columns (3×4 matrix, row-major), got {len(fields)}")
        T = np.eye(4)
        T[:3, :4] = _floats(fields, where).reshape(3, 4)
        R = T[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-4):
            raise TrajectoryFormatError(f"{where}: the 3×3 block is not a rotation matrix")
        poses.append(T)
    return np.stack(poses) if poses else np.zeros((0, 4, 4))


def write_kitti(path, poses) -> None:
    Path(path).write_text(format_kitti(poses))


def read_kitti(path) -> np.ndarray:
    p = Path(path)
    return parse_kitti(p.read_text(), source=str(p))
