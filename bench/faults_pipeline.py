"""The pipeline faults of bench/faults.py: the demo's services (all but the simulator) under `flyslam run`,
fed a simulated clip, through a 10× flood, hostile messages and a localiser killed with SIGKILL.

The clip (``common.sim.offline.cached_recording``: the corridor's scripted drive, JPEG frames) is read
once into msgpack maps; publishers (``workers`` processes, each every ``workers``-th message of one
schedule) restamp a map's envelope (seq, wall-clock stamp_ns), pack it and put it in a tight loop
paced by the clip's own times divided by the multiplier, so the content stays a robot's. A probe
subscriber counts the frames that really arrived: the rate reached is measured, not assumed.

- Flood: RSS (VmRSS of each service's process) through a warm-up, a nominal phase and a flood phase of
  equal length: ``nominal_rss_growth_mb`` is the growth over the nominal phase, ``flood_rss_growth_mb``
  the peak during the flood over the RSS at its start, per service, to be read side by side;
  ``flood_rss_excess_mb`` is what the flood adds to what the same time at the nominal rate grows (the
  flood's growth less the nominal phase's, the phases being equally long): the bridge's live viewer
  buffer grows with the images it logs at its own bounded rate (up to ``--server-memory-limit``), flood
  or not.
- Hostile messages (after the flood, the clip at its nominal rate): ``hostile`` (stream, payload)
  pairs cycled to ``hostile_count`` messages; ``hostile_crashes`` counts service restarts and services
  no longer running afterwards.
- Localiser restart: its process is SIGKILLed while it publishes poses and the supervisor restarts
  it. ``pose_gap_after_restart_s``: from the new process's start to its first slam/pose
  (``pose_gap_after_kill_s``: from the kill); ``trajectory_kept_fraction``: the poses of estimated.tum
  (all its segments) just before the kill that are still there after the run.
"""
from __future__ import annotations

import json
import multiprocessing as mp
import os
import signal
import subprocess
import time
import tomllib
from pathlib import Path

import msgpack

ROOT = Path(__file__).resolve().parent.parent
DEMO = ROOT / "deploy" / "launch" / "demo.toml"
CLIP_SECONDS = 20.0


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"no TOML for {v!r}")


def launch_without_sim(path: Path) -> list[str]:
    """demo.toml without its simulator (the flood replaces it), as TOML text; the names of its services."""
    data = tomllib.loads(DEMO.read_text())
    run = {k: v for k, v in data.get("run", {}).items() if k in ("latch",)}
    lines = ["[run]"] + [f"{k} = {_toml_value(v)}" for k, v in run.items()]
    lines += ["[vars]"] + [f"{k} = {_toml_value(v)}" for k, v in data.get("vars", {}).items()]
    names = []
    for svc in data["service"]:
        if svc["module"] == "services.sim":
            continue
        svc = dict(svc, start_delay_s=0.0)
        names.append(svc["name"])
        lines += ["[[service]]"] + [f"{k} = {_toml_value(v)}" for k, v in svc.items()]
    path.write_text("\n".join(lines) + "\n")
    return names


def load_clip() -> tuple[list[tuple[str, float, dict]], float]:
    """([(stream, clip time s, msgpack map)], clip period s) of the simulated clip, in time order."""
    from common.recording import RecordingReader
    from common.sim.offline import cached_recording

    recording = cached_recording("corridor", seconds=CLIP_SECONDS, encoding="jpeg")
    items = []
    for rec in RecordingReader(recording).messages():
        stream = rec.key.split("/", 1)[1]
        items.append((stream, rec.publish_time_ns, msgpack.unpackb(rec.payload, raw=False)))
    t0 = min(t for _, t, _ in items)
    items = sorted(((s, (t - t0) * 1e-9, obj) for s, t, obj in items), key=lambda x: x[1])
    return items, items[-1][1] + 0.1


def flood_worker(index: int, workers: int, hub: str, multiplier, stop, published) -> None:
    """Publish this worker's share of the clip's schedule until ``stop``; ``published[index]`` counts its
    stereo frames. The schedule is re-anchored when ``multiplier`` changes, so the clock never jumps."""
    from common import streams as S
    from common.bus import BusOptions, Node

    items, period = load_clip()
    per_stream: dict[str, int] = {}
    seq_base = []
    for stream, _, _ in items:
        seq_base.append(per_stream.get(stream, 0))
        per_stream[stream] = per_stream.get(stream, 0) + 1
    by_key = {s.key: s for s in vars(S).values() if isinstance(s, S.Stream)}
    with Node(f"faults-flood-{index}", BusOptions(hub=hub), handle_signals=False) as node:
        pubs = {stream: node.publisher(by_key[stream]) for stream in per_stream}
        time.sleep(1.0)
        k, mult = 0, multiplier.value
        anchor_wall, anchor_clip = time.monotonic(), 0.0
        while not stop.is_set():
            if multiplier.value != mult:   # re-anchor at the current clip position
                now = time.monotonic()
                anchor_clip += (now - anchor_wall) * mult
                anchor_wall, mult = now, multiplier.value
            i, cycle = k % len(items), k // len(items)
            k += 1
            if k % workers != index:
                continue
            stream, t_clip, obj = items[i]
            delay = anchor_wall + (cycle * period + t_clip - anchor_clip) / mult - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            obj["seq"] = cycle * per_stream[stream] + seq_base[i] + 1
            obj["stamp_ns"] = time.time_ns()
            pubs[stream].put_raw(msgpack.packb(obj, use_bin_type=True))
            if stream == "stereo/frame":
                published[index] += 1


def rss_mb(pid: int) -> float | None:
    try:
        for line in (Path("/proc") / str(pid) / "status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def _run_record(run: Path) -> dict:
    try:
        return json.loads((run / "run.json").read_text())
    except (OSError, ValueError):
        return {}



def boot_time_s() -> float:
    return time.clock_gettime(time.CLOCK_BOOTTIME)


def process_start_s(pid: int) -> float | None:
    """When process ``pid`` started, in seconds on CLOCK_BOOTTIME (field 22 of /proc/<pid>/stat)."""
    try:
        fields = (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()
        return int(fields[19]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


class Probe:
    """Counts the stereo frames that arrive; keeps (arrival time on CLOCK_BOOTTIME, stamp_ns) per slam/pose."""

    def __init__(self, node):
        self.frames = 0
        self.poses: list[tuple[float, int]] = []
        node.subscribe("stereo/frame", None, self._on_frame, raw=True)
        node.subscribe("slam/pose", None, self._on_pose, raw=True)

    def _on_frame(self, _key: str, _payload: bytes) -> None:
        self.frames += 1

    def _on_pose(self, _key: str, payload: bytes) -> None:
        obj = msgpack.unpackb(payload, raw=False)
        self.poses.append((boot_time_s(), obj.get("stamp_ns") if isinstance(obj, dict) else None))


class Pipeline:
    """demo.toml's services but the simulator under `flyslam run` in ``tmp/pipeline``, the clip's
    publishers (rate multiplier ``rate``), and a probe node on the same bus."""

    def __init__(self, tmp: Path, flyslam: list[str], env: dict, hub: str, workers: int):
        from common.bus import BusOptions, Node

        self.run, launch = tmp / "pipeline", tmp / "pipeline.toml"
        self.names = launch_without_sim(launch)
        load_clip()   # generate the cached clip once, before the workers read it
        self.sup = subprocess.Popen([*flyslam, "run", str(launch), "--out", str(self.run), "--duration", "0",
                                     "--hub", hub], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                                    stderr=subprocess.DEVNULL)
        ctx = mp.get_context("spawn")
        self.rate, self._stop = ctx.Value("d", 1.0), ctx.Event()
        self.published = ctx.Array("q", workers)
        self._workers = [ctx.Process(target=flood_worker, args=(i, workers, hub, self.rate, self._stop, self.published),
                                     daemon=True) for i in range(workers)]
        self.node = Node("faults-probe", BusOptions(hub=hub), handle_signals=False)
        self.probe = Probe(self.node)
        for p in self._workers:
            p.start()

    def services(self) -> dict:
        return _run_record(self.run).get("services", {})

    def wait_until_up(self, timeout: float = 120) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            services = self.services()
            if all("progress" in services.get(n, {}) for n in self.names):
                return True
            time.sleep(0.5)
        return False

    def sample_rss(self, samples: dict) -> None:
        services = self.services()
        for n in self.names:
            pid = services.get(n, {}).get("pid")
            if pid and (r := rss_mb(pid)) is not None:
                samples.setdefault(n, []).append((time.monotonic(), r))

    def stop(self) -> None:
        self._stop.set()
        for p in self._workers:
            p.join(10)
            if p.is_alive():
                p.kill()
        self.node.close()
        self.sup.send_signal(signal.SIGTERM)
        try:
            self.sup.wait(90)
        except subprocess.TimeoutExpired:
            self.sup.kill()


def measure_flood(pipe: Pipeline, phase_s: float, warmup_s: float, multiplier: float) -> dict:
    samples: dict[str, list[tuple[float, float]]] = {}
    marks: dict[str, tuple[float, int, int]] = {}
    for phase, seconds, mult in [("warmup", warmup_s, 1.0), ("nominal", phase_s, 1.0), ("flood", phase_s, multiplier)]:
        pipe.rate.value = mult
        marks[phase] = (time.monotonic(), pipe.probe.frames, sum(pipe.published))
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            pipe.sample_rss(samples)
            time.sleep(0.5)
    marks["end"] = (time.monotonic(), pipe.probe.frames, sum(pipe.published))
    pipe.rate.value = 1.0

    def rate_in(phase: str, nxt: str, which: int) -> float:
        (t_a, *a), (t_b, *b) = marks[phase], marks[nxt]
        return round((b[which] - a[which]) / max(t_b - t_a, 1e-9), 1)

    def rss_at(n: str, t: float) -> float | None:
        before = [r for ts, r in samples.get(n, []) if ts <= t]
        return before[-1] if before else None

    t_nominal, t_flood, t_end = marks["nominal"][0], marks["flood"][0], marks["end"][0]
    growth_nominal, growth_flood, rss_nominal = {}, {}, {}
    for n in pipe.names:
        start, at_flood = rss_at(n, t_nominal), rss_at(n, t_flood)
        peak = max((r for ts, r in samples.get(n, []) if t_flood <= ts <= t_end), default=None)
        rss_nominal[n] = None if at_flood is None else round(at_flood, 1)
        growth_nominal[n] = None if start is None or at_flood is None else round(at_flood - start, 1)
        growth_flood[n] = None if peak is None or at_flood is None else round(peak - at_flood, 1)
    excess = {n: None if growth_flood[n] is None or growth_nominal[n] is None
              else round(growth_flood[n] - max(growth_nominal[n], 0.0), 1) for n in pipe.names}
    services = pipe.services()
    nominal_hz, flood_hz = rate_in("nominal", "flood", 0), rate_in("flood", "end", 0)
    return {"flood_multiplier_asked": multiplier, "flood_publishers": len(pipe.published), "flood_phase_s": phase_s,
            "nominal_frame_hz_received": nominal_hz, "flood_frame_hz_published": rate_in("flood", "end", 1),
            "flood_frame_hz_received": flood_hz,
            "flood_multiplier_reached": round(flood_hz / nominal_hz, 2) if nominal_hz else None,
            "rss_at_end_of_nominal_mb": rss_nominal, "nominal_rss_growth_mb": growth_nominal,
            "flood_rss_growth_mb": growth_flood,
            "flood_rss_excess_mb": excess,
            "flood_rss_excess_max_mb": max((v for v in excess.values() if v is not None), default=None),
            "flood_restarts": {n: services.get(n, {}).get("restarts") for n in pipe.names},
            "flood_dropped": {"recorder": services.get("recorder", {}).get("counters", {}).get("dropped", 0),
                              "bridge": services.get("bridge", {}).get("counters", {}).get("inbox_dropped", 0)}}


def _restarts_and_down(pipe: Pipeline) -> tuple[int, int]:
    services = pipe.services()
    return (sum(services.get(n, {}).get("restarts", 0) for n in pipe.names),
            sum(services.get(n, {}).get("state") != "running" for n in pipe.names))


def _rejected(pipe: Pipeline) -> int:
    return sum(int(s.get("counters", {}).get("rejected", 0)) for s in pipe.services().values())


def send_hostile(pipe: Pipeline, hostile: list[tuple[str, bytes]], count: int, rate_hz: float = 2000.0) -> dict:
    """Publish ``count`` hostile payloads, cycling through ``hostile``, while the clip plays at its nominal rate."""
    restarts_before, _ = _restarts_and_down(pipe)
    rejected_before = _rejected(pipe)
    pubs = {}
    t0 = time.monotonic()
    for i in range(count):
        stream, payload = hostile[i % len(hostile)]
        key = "status/hostile" if "*" in stream else stream
        if key not in pubs:
            pubs[key] = pipe.node.publisher(key, reliable=True)
        pubs[key].put_raw(payload)
        if (delay := t0 + (i + 1) / rate_hz - time.monotonic()) > 0:
            time.sleep(delay)
    time.sleep(5.0)   # heartbeats (every second) report the rejections; a crashed service shows as restarted
    restarts_after, down = _restarts_and_down(pipe)
    return {"hostile_messages": count, "hostile_cases": len(hostile),
            "hostile_crashes": restarts_after - restarts_before + down,
            "hostile_rejected_counted": _rejected(pipe) - rejected_before}


def _tum_stamps(base: Path) -> set[int]:
    from common.recording import segments_of
    from common.trajectory import TrajectoryFormatError, read_tum

    stamps: set[int] = set()
    for path in segments_of(base):
        try:
            stamps |= set(read_tum(path)[0].tolist())
        except (OSError, TrajectoryFormatError):
            pass
    return stamps


def kill_localiser(pipe: Pipeline, wait_s: float = 60.0) -> tuple[dict, set[int]]:
    """SIGKILL the localiser once it publishes poses and its estimated.tum holds some; measure how soon the
    restarted one publishes. Returns (figures, the stamps estimated.tum held before the kill)."""
    tum = pipe.run / "estimated.tum"
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline and not (_tum_stamps(tum) and pipe.probe.poses
                                                and boot_time_s() - pipe.probe.poses[-1][0] < 2.0):
        time.sleep(0.5)
    before = _tum_stamps(tum)
    old_pid = pipe.services().get("localiser", {}).get("pid")
    if not before or not old_pid:
        return {"pose_gap_after_restart_s": None, "localiser_restart_skipped": "the localiser wrote no poses"}, before
    time.sleep(5.5)   # one more periodic TUM write: the kill then lands between two of them
    before = _tum_stamps(tum)
    os.kill(old_pid, signal.SIGKILL)
    t_kill = boot_time_s()
    new_pid = None
    while boot_time_s() - t_kill < wait_s:
        pid = pipe.services().get("localiser", {}).get("pid")
        new_pid = pid if pid != old_pid else None
        first = next((t for t, _ in reversed(pipe.probe.poses) if t > t_kill + 0.1), None)
        if new_pid and first is not None:
            break
        time.sleep(0.1)
    after = [t for t, _ in pipe.probe.poses if t > t_kill + 0.1]
    started = process_start_s(new_pid) if new_pid else None
    figures = {"pose_gap_after_kill_s": round(after[0] - t_kill, 2) if after else None,
               "pose_gap_after_restart_s": round(after[0] - started, 2) if after and started else None}
    return figures, before


def pipeline_faults(tmp: Path, flyslam: list[str], env: dict, hub: str, phase_s: float, warmup_s: float,
                    hostile: list[tuple[str, bytes]], hostile_count: int, multiplier: float = 10.0,
                    workers: int = 2) -> dict:
    t0 = time.monotonic()
    pipe = Pipeline(tmp, flyslam, env, hub, workers)
    result: dict = {}
    try:
        result["pipeline_up"] = pipe.wait_until_up()
        result.update(measure_flood(pipe, phase_s, warmup_s, multiplier))
        result.update(send_hostile(pipe, hostile, hostile_count))
        restart, before = kill_localiser(pipe)
        result.update(restart)
        time.sleep(10.0)
    finally:
        pipe.stop()
    if before:
        kept = _tum_stamps(pipe.run / "estimated.tum")
        result["trajectory_kept_fraction"] = round(len(before & kept) / len(before), 4)
        result["estimated_poses_before_kill"], result["estimated_poses_at_end"] = len(before), len(kept)
    else:
        result["trajectory_kept_fraction"] = None
    result["pipeline_seconds"] = round(time.monotonic() - t0, 1)
    return result
