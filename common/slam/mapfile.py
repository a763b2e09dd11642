"""The fly map on disk: ``map.mcap``, a flyslam recording (common.recording) holding

- ``map/keyframes``: one ``flyslam.FlyMap`` message per keyframe (the bus's own schema, so the tools that
  show ``slam/map`` read it): id, stamp, T_map_base as position + xyzw quaternion, the population's
  points (K, 3) float32 in that keyframe's base_link and their fitness (K,) float32, and the keyframe's
  grey left image at half resolution when it kept one (its loops are aligned on it);
- ``map/graph``: one ``flyslam.PoseEstimate`` per pose-graph edge, because an edge is exactly that:
  the pose of keyframe j (``child_frame_id = "keyframe/<j>"``) in keyframe i (``frame_id =
  "keyframe/<i>"``, or ``"map"`` for a prior), with its 6×6 covariance in flyslam's (x, y, z, rx, ry, rz)
  order (see common.slam.posegraph); ``status`` is "<kind> robust" or "<kind> quadratic" (kind:
  odometry, registration, prior).  No new schema: every message in the file is one the bus knows.
- metadata ``flyslam.map``, written last: format version, keyframe and edge counts (a file that lost
  messages is refused, not half-loaded), the caller's ``meta`` as JSON and a CRC-32 over the payloads and
  the meta (MCAP checks its chunks, not its metadata).

Everything round-trips bit for bit except rotations (keyframes' and edges'), which go through a
quaternion (≈1e-16).  :func:`save_map` writes a temporary file and renames it, so a process killed
mid-save leaves the previous map intact.  :func:`load_map` turns every problem into one
:class:`MapFileError` line.
"""
from __future__ import annotations

import json
import os
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common import messages as m
from common.geometry import pose_from_transform, transform_from_pose
from common.recording import RecordingError, RecordingReader, RecordingWriter

FORMAT = "flyslam-map"
VERSION = 1
KEYFRAMES_KEY = "map/keyframes"
GRAPH_KEY = "map/graph"
MAP_METADATA = "flyslam.map"
EDGE_KINDS = ("odometry", "registration", "prior")


class MapFileError(ValueError):
    """A map that cannot be saved or loaded; the one-line message names the file and the problem."""


@dataclass
class MapKeyframe:
    id: int
    stamp_ns: int
    T_map_base: np.ndarray    # 4×4
    points: np.ndarray        # (K, 3) float32 in this keyframe's base_link
    fitness: np.ndarray       # (K,) float32
    image: np.ndarray | None = None   # grey left image at half resolution (photometric loops), or None


@dataclass
class MapEdge:
    i: int
    j: int
    T_i_j: np.ndarray
    cov: np.ndarray
    kind: str
    robust: bool = True


@dataclass
class FlyMapData:
    keyframes: list[MapKeyframe]
    edges: list[MapEdge]
    meta: dict


# ------------------------------------------------------------------------------------- saving


def _keyframe_msg(kf) -> m.FlyMap:
    T = np.asarray(kf.T_map_base, dtype=float)
    pts = np.asarray(kf.points)
    fit = np.asarray(kf.fitness)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise MapFileError(f"keyframe {kf.id}: T_map_base must be a finite 4×4 transform")
    if pts.ndim != 2 or pts.shape[1] != 3 or fit.shape != (len(pts),):
        raise MapFileError(f"keyframe {kf.id}: points must be (K, 3) and fitness (K,), got "
                           f"{pts.shape} and {fit.shape}")
    p, q = pose_from_transform(T)
    image = getattr(kf, "image", None)
    image = None if image is None else np.ascontiguousarray(image)
    if image is not None and (image.ndim != 2 or image.dtype != np.uint8 or image.size == 0):
        raise MapFileError(f"keyframe {kf.id}: image must be a grey uint8 H×W array, got {image.shape}")
    msg = m.Keyframe(id=int(kf.id), stamp_ns=int(kf.stamp_ns), position=p, orientation=q,
                     points=pts.astype(np.float32, copy=False), fitness=fit.astype(np.float32, copy=False),
                     image=image)
    return m.FlyMap(keyframes=[msg], header=m.header(int(kf.id), int(kf.stamp_ns), m.MAP))


def _frame(kf_id: int) -> str:
    return f"keyframe/{kf_id}"


def _edge_msg(e, seq: int, stamp_ns: int) -> m.PoseEstimate:
    T = np.asarray(e.T_i_j, dtype=float)
    cov = np.asarray(e.cov, dtype=float)
    if T.shape != (4, 4) or cov.shape != (6, 6) or not np.all(np.isfinite(T)):
        raise MapFileError(f"edge {e.i}→{e.j}: T_i_j must be a finite 4×4 and cov 6×6, got {T.shape} and {cov.shape}")
    kind = str(e.kind)
    if kind not in EDGE_KINDS:
        raise MapFileError(f"edge {e.i}→{e.j}: kind {e.kind!r}, expected one of {', '.join(EDGE_KINDS)}")
    if (kind == "prior") != (int(e.i) == int(e.j)):
        raise MapFileError(f"edge {e.i}→{e.j}: a prior has i == j, any other edge i != j")
    robust = bool(getattr(e, "robust", True))
    return m.pose_msg(T, cov, seq=seq, stamp_ns=stamp_ns, frame_id=m.MAP if kind == "prior" else _frame(int(e.i)),
                      child=_frame(int(e.j)), status=f"{kind} {'robust' if robust else 'quadratic'}")


def _edge_from_msg(msg: m.PoseEstimate) -> MapEdge:
    """Raises ValueError on an edge message this module did not write."""
    kind, _, weighting = msg.status.partition(" ")
    if kind not in EDGE_KINDS or weighting not in ("robust", "quadratic"):
        raise ValueError(f"edge status {msg.status!r}")
    j = _frame_id(msg.child_frame_id)
    i = j if msg.header.frame_id == m.MAP else _frame_id(msg.header.frame_id)
    if (kind == "prior") != (msg.header.frame_id == m.MAP):
        raise ValueError(f"edge {msg.header.frame_id} → {msg.child_frame_id} of kind {kind}")
    return MapEdge(i, j, m.transform_of(msg), msg.covariance.copy(), kind, weighting == "robust")


def _frame_id(frame: str) -> int:
    prefix, _, number = frame.partition("/")
    if prefix != "keyframe" or not number.isdigit():
        raise ValueError(f"edge frame {frame!r} is not keyframe/<id>")
    return int(number)


def save_map(path: str | Path, keyframes, edges, meta: dict | None = None) -> Path:
    """Write the map to ``path`` (normally ``<run folder>/map.mcap``).  ``keyframes``: objects with id,
    stamp_ns, T_map_base, points, fitness (common.slam.Keyframe or MapKeyframe); ``edges``: objects with
    i, j, T_i_j, cov, kind and optionally robust (common.slam.posegraph.Edge or MapEdge), each naming
    keyframes of the map; ``meta``: JSON-serialisable (e.g. the localiser's configuration)."""
    path = Path(path)
    keyframes = list(keyframes)
    edges = list(edges.values() if isinstance(edges, dict) else edges)   # PoseGraph.edges() is a dict
    for what, items, fields in (("keyframe", keyframes, ("id", "stamp_ns", "T_map_base", "points", "fitness")),
                                ("edge", edges, ("i", "j", "T_i_j", "cov", "kind"))):
        for item in items:
            missing = [f for f in fields if not hasattr(item, f)]
            if missing:
                raise MapFileError(f"{path}: a {what} without {', '.join(missing)} ({type(item).__name__})")
    ids = [int(kf.id) for kf in keyframes]
    if len(set(ids)) != len(ids):
        raise MapFileError(f"{path}: duplicate keyframe ids")
    kf_msgs = [_keyframe_msg(kf) for kf in keyframes]
    known = set(ids)
    for e in edges:
        if int(e.i) not in known or int(e.j) not in known:
            raise MapFileError(f"{path}: edge {e.i}→{e.j} names a keyframe that is not in the map")
    try:
        meta_json = json.dumps(meta or {}, sort_keys=True)
    except (TypeError, ValueError) as e:
        raise MapFileError(f"{path}: meta is not JSON-serialisable ({e})") from None
    stamp = max([int(kf.stamp_ns) for kf in keyframes], default=0)
    edge_msgs = [_edge_msg(e, n, stamp) for n, e in enumerate(edges)]
    tmp = path.with_name(path.name + ".tmp")
    payloads = [(KEYFRAMES_KEY, m.encode(msg), msg.header.stamp_ns) for msg in kf_msgs]
    payloads += [(GRAPH_KEY, m.encode(msg), stamp) for msg in edge_msgs]
    with RecordingWriter(tmp) as w:
        for key, payload, stamp_ns in payloads:
            w.write(key, payload, stamp_ns)
        w.add_metadata(MAP_METADATA, {"format": FORMAT, "version": VERSION, "keyframes": len(kf_msgs),
                                      "edges": len(edge_msgs), "meta": meta_json,
                                      "crc32": _crc([p for _, p, _ in payloads], meta_json)})
    os.replace(tmp, path)
    return path


# ------------------------------------------------------------------------------------ loading


def load_map(path: str | Path) -> FlyMapData:
    """Read a map written by :func:`save_map`; raises :class:`MapFileError` (one line) on anything wrong."""
    path = Path(path)
    try:
        reader = RecordingReader(path)
        records = list(reader.messages(keys={KEYFRAMES_KEY, GRAPH_KEY}))
    except (RecordingError, OSError) as e:
        raise MapFileError(f"cannot read map: {e}") from None
    if reader.error:
        raise MapFileError(f"{path}: damaged map file ({reader.error})")
    info = reader.metadata.get(MAP_METADATA)
    if info is None or info.get("format") != FORMAT:
        raise MapFileError(f"{path}: not a flyslam map (no '{MAP_METADATA}' metadata)")
    if info.get("version") != str(VERSION):
        raise MapFileError(f"{path}: map format version {info.get('version')}, this build reads {VERSION}")
    if info.get("crc32") != _crc([r.payload for r in records], info.get("meta", "")):
        raise MapFileError(f"{path}: damaged map file (checksum mismatch)")
    keyframes, edges = [], []
    try:
        for rec in records:
            if rec.key == KEYFRAMES_KEY:
                for kf in m.decode(rec.payload, m.FlyMap).keyframes:
                    keyframes.append(MapKeyframe(kf.id, kf.stamp_ns, transform_from_pose(kf.position, kf.orientation),
                                                 kf.points.copy(), kf.fitness.copy(),
                                                 None if kf.image is None else kf.image.copy()))
            else:
                edges.append(_edge_from_msg(m.decode(rec.payload, m.PoseEstimate)))
        meta = json.loads(info.get("meta", "{}"))
        n_kf, n_edges = int(info.get("keyframes", -1)), int(info.get("edges", -1))
    except (m.DecodeError, ValueError) as e:
        raise MapFileError(f"{path}: corrupt map record ({_one_line(e)})") from None
    if len(keyframes) != n_kf or len(edges) != n_edges:
        raise MapFileError(f"{path}: map incomplete: {len(keyframes)}/{n_kf} keyframes, "
                           f"{len(edges)}/{n_edges} edges")
    known = {kf.id for kf in keyframes}
    for e in edges:
        if e.i not in known or e.j not in known:
            raise MapFileError(f"{path}: edge {e.i}→{e.j} ({e.kind}) does not fit the map's keyframes")
    return FlyMapData(keyframes, edges, meta if isinstance(meta, dict) else {"meta": meta})


def _crc(payloads: list[bytes], meta_json: str) -> str:
    crc = 0
    for p in payloads:
        crc = zlib.crc32(p, crc)
    return f"{zlib.crc32(meta_json.encode(), crc):08x}"


def _one_line(e: Exception) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__
