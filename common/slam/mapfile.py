"""The fly map on disk: ``map.mcap``, a flyslam recording (common.recording) holding

- ``map/keyframes``: one ``flyslam.FlyMap`` message per keyframe (the bus's own schema, so the tools that
  show ``slam/map`` read it): id, stamp, T_map_base as position + xyzw quaternion, the population's
  points (K, 3) float32 in that keyframe's base_link and their fitness (K,) float32;
- ``map/graph``: one ``flyslam.MapGraph`` message (defined here: nothing on the bus carries the graph)
  with the pose graph's edges: i, j, T_i_j (4×4, exact), 6×6 covariance in flyslam's (x, y, z, rx, ry, rz)
  order (see common.slam.posegraph), kind ('odometry', 'registration', 'prior') and robust;
- metadata ``flyslam.map``, written last: format version, keyframe and edge counts (a file that lost
  messages is refused, not half-loaded), the caller's ``meta`` as JSON and a CRC-32 over the payloads and
  the meta (MCAP checks its chunks, not its metadata).

Everything round-trips bit for bit except a keyframe's rotation, which goes through a quaternion
(≈1e-16).  :func:`save_map` writes a temporary file and renames it, so a process killed mid-save leaves
the previous map intact.  :func:`load_map` turns every problem into one :class:`MapFileError` line.
"""
from __future__ import annotations

import json
import os
import zlib
from dataclasses import dataclass, field
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


@m.schema("MapEdge")
class MapEdgeMsg:
    """One pose-graph edge: T_i_j maps keyframe j's base_link into keyframe i's (a prior: i == j and
    T_i_j is T_map_i); covariance over (x, y, z, rx, ry, rz) in frame j."""
    i: int = 0
    j: int = 0
    T_i_j: np.ndarray = m.array_field("float64", (4, 4))
    covariance: np.ndarray = m.array_field("float64", (6, 6))
    kind: str = "registration"
    robust: bool = True


@m.schema("MapGraph")
class MapGraph(m.Message):
    """The fly map's pose graph (frame_id = map)."""
    edges: list[MapEdgeMsg] = field(default_factory=list)
    header: m.Envelope = field(default_factory=m.Envelope)


@dataclass
class MapKeyframe:
    id: int
    stamp_ns: int
    T_map_base: np.ndarray    # 4×4
    points: np.ndarray        # (K, 3) float32 in this keyframe's base_link
    fitness: np.ndarray       # (K,) float32


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
    msg = m.Keyframe(id=int(kf.id), stamp_ns=int(kf.stamp_ns), position=p, orientation=q,
                     points=pts.astype(np.float32, copy=False), fitness=fit.astype(np.float32, copy=False))
    return m.FlyMap(keyframes=[msg], header=m.header(int(kf.id), int(kf.stamp_ns), m.MAP))


def _edge_msg(e) -> MapEdgeMsg:
    T = np.asarray(e.T_i_j, dtype=float)
    cov = np.asarray(e.cov, dtype=float)
    if T.shape != (4, 4) or cov.shape != (6, 6):
        raise MapFileError(f"edge {e.i}→{e.j}: T_i_j must be 4×4 and cov 6×6, got {T.shape} and {cov.shape}")
    if str(e.kind) not in EDGE_KINDS:
        raise MapFileError(f"edge {e.i}→{e.j}: kind {e.kind!r}, expected one of {', '.join(EDGE_KINDS)}")
    return MapEdgeMsg(i=int(e.i), j=int(e.j), T_i_j=T, covariance=cov, kind=str(e.kind),
                      robust=bool(getattr(e, "robust", True)))


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
    edge_msgs = [_edge_msg(e) for e in edges]
    known = set(ids)
    for e in edge_msgs:
        if e.i not in known or e.j not in known:
            raise MapFileError(f"{path}: edge {e.i}→{e.j} names a keyframe that is not in the map")
    try:
        meta_json = json.dumps(meta or {}, sort_keys=True)
    except (TypeError, ValueError) as e:
        raise MapFileError(f"{path}: meta is not JSON-serialisable ({e})") from None
    stamp = max([int(kf.stamp_ns) for kf in keyframes], default=0)
    tmp = path.with_name(path.name + ".tmp")
    payloads = [(KEYFRAMES_KEY, m.encode(msg), msg.header.stamp_ns) for msg in kf_msgs]
    payloads.append((GRAPH_KEY, m.encode(MapGraph(edges=edge_msgs, header=m.header(0, stamp, m.MAP))), stamp))
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
                                                 kf.points.copy(), kf.fitness.copy()))
            else:
                for e in m.decode(rec.payload, MapGraph).edges:
                    edges.append(MapEdge(e.i, e.j, e.T_i_j.copy(), e.covariance.copy(), e.kind, e.robust))
        meta = json.loads(info.get("meta", "{}"))
        n_kf, n_edges = int(info.get("keyframes", -1)), int(info.get("edges", -1))
    except (m.DecodeError, ValueError) as e:
        raise MapFileError(f"{path}: corrupt map record ({_one_line(e)})") from None
    if len(keyframes) != n_kf or len(edges) != n_edges:
        raise MapFileError(f"{path}: map incomplete: {len(keyframes)}/{n_kf} keyframes, "
                           f"{len(edges)}/{n_edges} edges")
    for kf in keyframes:
        if len(kf.points) != len(kf.fitness):
            raise MapFileError(f"{path}: keyframe {kf.id} has {len(kf.points)} points but "
                               f"{len(kf.fitness)} fitness values")
    known = {kf.id for kf in keyframes}
    for e in edges:
        if e.i not in known or e.j not in known or e.kind not in EDGE_KINDS:
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
