"""`flyslam run`: start the services of a launch file as OS processes and supervise them.

A launch file (TOML, see ``deploy/launch/``) lists services in start order::

    [run]
    duration_s = 30                 # default bound; --duration overrides, 0 = until Ctrl-C
    latch = ["fusion/odom"]         # streams the supervisor keeps and serves to queries, so a restarted
                                    # service finds its last state on the bus though its publisher died
    report = "pipeline"             # optional: print the pipeline summary (deploy/report.py) at the end
    [[service]]
    name = "recorder"
    module = "services.recorder"    # started as: python -P -m <module> <args> <bus flags>, in the folder
                                    # `flyslam run` was started from (relative paths mean what the user typed)
    args = ["--out", "{out}/recording.mcap"]
    restart = "on-failure"          # never | on-failure | always
    max_restarts = 3                # then the service has given up
    backoff_s = 0.5                 # first restart delay, doubled on each restart (max 30 s)
    required = true                 # a required service that gives up fails the run
    ends_run = false                # when it exits 0, the whole run stops (e.g. a replay that finished)
    liveliness_timeout_s = 20       # alive process without a liveliness token this long = hung, restarted
    stop_timeout_s = 10             # SIGTERM, then SIGKILL after this long
    nice = 0                        # raise the process's niceness (0-19) once it is up (liveliness
                                    # token seen; it starts at full priority so that a loaded machine
                                    # cannot starve its start-up past liveliness_timeout_s): services
                                    # off the critical path (viewer bridge, recorder) yield the CPU
    start_delay_s = 0               # wait this long after starting it before starting the next
    wait_for_ready = false          # start it only once every service before it is up (its liveliness
                                    # token seen; at most their liveliness_timeout_s): a replay or a video
                                    # must not play to an evolver still loading its kernels

``{out}``, ``{root}`` and ``{recordings}`` are substituted in args, and so are the launch file's own
``[vars]`` (defaults) as overridden by ``--var NAME=VALUE`` on the command line. Services stop in the reverse of start
order (so list the recorder first: it stops last and records everything). The supervisor opens its own
bus session first (it becomes the local hub), watches every service's liveliness token and heartbeat,
and writes per-service logs and ``run.json`` under ``--out``: written as the run starts and rewritten
(atomically) whenever a service starts, exits or restarts, so a supervisor killed with SIGKILL still
leaves a readable record.

No orphans: every service runs in its own process group, killed as a group when the service exits (a
dead bridge's ``rerun --serve-web`` child must not keep its port). Children get PR_SET_PDEATHSIG
(SIGTERM when the supervisor dies, whatever killed it), and a watchdog process, in its own session,
holds the list of live groups through a pipe: when the pipe closes without a goodbye (the supervisor
was SIGKILLed), it SIGTERMs every group, SIGKILLs what is left after a grace period, grandchildren
included, marks ``run.json`` and writes the run's ``summary.json`` if the launch file asks for one. A service
that exits with status 2 (a bad file or flag, by flyslam's convention) is not restarted: it would fail
the same way; its last log line (its one-line error) is shown. Exit status: 0, or 1 when a required
service gave up, 2 for a bad launch file or flag.
"""
from __future__ import annotations

import argparse
import ctypes
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import zenoh

from common.bus import BusConfigError, Node, add_bus_arguments, bus_options, services_alive, setup_logging
from common.messages import DecodeError, Heartbeat, decode

log = logging.getLogger("flyslam.supervisor")

ROOT = Path(__file__).resolve().parent.parent
BAD_INPUT_STATUS = 2      # a flyslam command's exit status for a bad file or flag
DEFAULT_LAUNCH = ROOT / "deploy" / "launch" / "demo.toml"
RESTART_POLICIES = ("never", "on-failure", "always")


class LaunchError(ValueError):
    """A launch file that cannot be used; the message names the file and the field."""


@dataclass
class ServiceSpec:
    name: str
    module: str
    args: list[str] = field(default_factory=list)
    restart: str = "on-failure"
    max_restarts: int = 3
    backoff_s: float = 0.5
    required: bool = True
    ends_run: bool = False
    liveliness_timeout_s: float = 20.0
    stop_timeout_s: float = 10.0
    start_delay_s: float = 0.0
    wait_for_ready: bool = False
    nice: int = 0


@dataclass
class LaunchFile:
    path: Path
    duration_s: float
    services: list[ServiceSpec]
    robot: str | None = None
    vars: dict[str, str] = field(default_factory=dict)
    latch: list[str] = field(default_factory=list)
    report: str | None = None


# field -> (kind, expected), kinds checked by _check_field; bool is never taken for a number
SERVICE_FIELDS = {
    "name": ("str", "a string"), "module": ("str", "a module name (string)"),
    "args": ("strlist", "a list of strings"), "restart": ("str", f"one of {', '.join(RESTART_POLICIES)}"),
    "max_restarts": ("count", "an integer ≥ 0"), "backoff_s": ("seconds", "a number of seconds ≥ 0"),
    "required": ("bool", "true or false"), "ends_run": ("bool", "true or false"),
    "liveliness_timeout_s": ("seconds", "a number of seconds ≥ 0 (0: not checked)"),
    "stop_timeout_s": ("seconds", "a number of seconds ≥ 0"),
    "start_delay_s": ("seconds", "a number of seconds ≥ 0"), "nice": ("nice", "an integer in 0..19"),
    "wait_for_ready": ("bool", "true or false"),
}
RUN_FIELDS = {
    "duration_s": ("seconds", "a number of seconds ≥ 0 (0: until stopped)"), "robot": ("str", "a string"),
    "latch": ("strlist", "a list of stream names"), "report": ("report", '"pipeline" or absent'),
}


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _field_ok(kind: str, v) -> bool:
    return {
        "str": lambda: isinstance(v, str) and v != "",
        "strlist": lambda: isinstance(v, list) and all(isinstance(a, str) for a in v),
        "count": lambda: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
        "seconds": lambda: _is_number(v) and v >= 0 and v == v and v != float("inf"),
        "bool": lambda: isinstance(v, bool),
        "nice": lambda: isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 19,
        "report": lambda: v == "pipeline",
    }[kind]()


def _check_fields(where: str, table: dict, fields: dict) -> None:
    for key, value in table.items():
        if key not in fields:
            raise LaunchError(f"{where}: unknown field '{key}'; allowed: {', '.join(fields)}")
        kind, expected = fields[key]
        if not _field_ok(kind, value):
            raise LaunchError(f"{where}: {key} must be {expected}, got {value!r}")


def load_launch(path: Path) -> LaunchFile:
    """Read and check a launch file; every problem is a LaunchError naming the file, the field and the
    expected type (a wrong type fails here, not when the service first fails)."""
    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise LaunchError(f"{path}: launch file not found") from None
    except IsADirectoryError:
        raise LaunchError(f"{path}: is a directory, not a launch file (TOML)") from None
    except OSError as e:
        raise LaunchError(f"{path}: cannot read launch file ({e.strerror or e})") from None
    except UnicodeDecodeError as e:
        raise LaunchError(f"{path}: not UTF-8 text (byte {e.start}); a launch file is TOML") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise LaunchError(f"{path}: not valid TOML ({e})") from None
    unknown = set(data) - {"run", "service", "vars"}
    if unknown:
        raise LaunchError(f"{path}: unknown table(s) {', '.join(sorted(unknown))}; allowed: run, service, vars")
    run = data.get("run", {})
    if not isinstance(run, dict):
        raise LaunchError(f"{path}: run must be a table ([run]), got {run!r}")
    _check_fields(f"{path}: [run]", run, RUN_FIELDS)
    raw_services = data.get("service", [])
    if not isinstance(raw_services, list) or not all(isinstance(r, dict) for r in raw_services):
        raise LaunchError(f"{path}: service must be an array of tables ([[service]]), got {raw_services!r}")
    services = []
    for i, raw in enumerate(raw_services):
        where = f"{path}: service #{i + 1}" + (f" ({raw['name']})" if isinstance(raw.get("name"), str) else "")
        for req in ("name", "module"):
            if req not in raw:
                raise LaunchError(f"{where}: missing '{req}'")
        _check_fields(where, raw, SERVICE_FIELDS)
        if raw.get("restart", "on-failure") not in RESTART_POLICIES:
            raise LaunchError(f"{where}: restart must be one of {RESTART_POLICIES}, got {raw['restart']!r}")
        services.append(ServiceSpec(**raw))
    if not services:
        raise LaunchError(f"{path}: no [[service]] entries")
    names = [s.name for s in services]
    if len(set(names)) != len(names):
        raise LaunchError(f"{path}: service names must be unique, got {names}")
    raw_vars = data.get("vars", {})
    if not isinstance(raw_vars, dict):
        raise LaunchError(f"{path}: vars must be a table ([vars]), got {raw_vars!r}")
    for k, v in raw_vars.items():
        if not isinstance(v, (str, int, float)) or isinstance(v, bool):
            raise LaunchError(f"{path}: [vars] {k} must be a string or a number, got {v!r}")
    variables = {str(k): str(v) for k, v in raw_vars.items()}
    return LaunchFile(path, float(run.get("duration_s", 0)), services, run.get("robot"), variables,
                      list(run.get("latch", [])), run.get("report"))


# ----------------------------------------------------------------------------------- children


WATCHDOG_GRACE_S = 2.0
# Run as `python -I -c WATCHDOG_SOURCE <run.json> <grace_s> [<JSON argv>]` with the supervisor writing to
# its stdin: "+<pgid>" a group to kill if the supervisor dies, "-<pgid>" a group already reaped, "bye" a
# normal end. After a supervisor's death it runs the optional argv (the run's summary.json report).
WATCHDOG_SOURCE = r"""
import json, os, signal, subprocess, sys, time
record, grace = sys.argv[1], float(sys.argv[2])
after = json.loads(sys.argv[3]) if len(sys.argv) > 3 else None
groups, normal_end = set(), False
for line in iter(sys.stdin.buffer.readline, b""):
    line = line.strip().decode()
    if line == "bye":
        normal_end = True
    elif line[:1] in "+-" and line[1:].isdigit():
        (groups.add if line[0] == "+" else groups.discard)(int(line[1:]))
def alive(g):
    try:
        os.killpg(g, 0)
        return True
    except OSError:
        return False
def signal_all(sig):
    for g in list(groups):
        try:
            os.killpg(g, sig)
        except OSError:
            groups.discard(g)
signal_all(signal.SIGTERM)
deadline = time.monotonic() + grace
while any(alive(g) for g in groups) and time.monotonic() < deadline:
    time.sleep(0.05)
signal_all(signal.SIGKILL)
if not normal_end:
    try:
        with open(record) as f:
            run = json.load(f)
        run["state"] = "supervisor-died"
        run["stop_reason"] = "the supervisor died without stopping its services (SIGKILL?); its watchdog killed them"
        for s in run.get("services", {}).values():
            if s.get("state") in ("running", "backoff", "pending"):
                s["state"] = "killed"
        with open(record + ".tmp", "w") as f:
            json.dump(run, f, indent=2)
        os.replace(record + ".tmp", record)
    except (OSError, ValueError):
        pass
    if after:
        try:
            subprocess.run(after, timeout=120)
        except (OSError, subprocess.SubprocessError) as e:
            print(f"watchdog: {after[:3]} failed: {e}", file=sys.stderr)
"""
# The report a run writes at its end (summary.json), run by the watchdog when the supervisor could not.
REPORT_SOURCE = ("import json, sys; from pathlib import Path; from deploy.report import pipeline_summary; "
                 "out = Path(sys.argv[1]); (out / 'summary.json').write_text(json.dumps(pipeline_summary(out), indent=2))")


class Watchdog:
    """The process that kills every service's group if the supervisor dies (see the module docstring)."""

    def __init__(self, record: Path, log_path: Path, grace_s: float = WATCHDOG_GRACE_S,
                 after: list[str] | None = None, env: dict | None = None):
        argv = [sys.executable, "-I", "-c", WATCHDOG_SOURCE, str(record), str(grace_s)]
        with open(log_path, "ab") as logf:
            self.proc = subprocess.Popen(argv + ([json.dumps(after)] if after else []), stdin=subprocess.PIPE,
                                         stdout=logf, stderr=subprocess.STDOUT, start_new_session=True, env=env,
                                         cwd=ROOT)

    def _send(self, line: str) -> None:
        try:
            self.proc.stdin.write(f"{line}\n".encode())
            self.proc.stdin.flush()
        except (BrokenPipeError, ValueError):
            log.warning("the watchdog has gone: services would outlive a killed supervisor")

    def watch(self, pgid: int) -> None:
        self._send(f"+{pgid}")

    def forget(self, pgid: int) -> None:
        self._send(f"-{pgid}")

    def close(self) -> None:
        self._send("bye")
        try:
            self.proc.stdin.close()
        except (BrokenPipeError, OSError):
            pass
        try:
            self.proc.wait(WATCHDOG_GRACE_S + 5)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def kill_group(pgid: int) -> None:
    """SIGKILL what is left of a service's process group (its leader has exited)."""
    try:
        os.killpg(pgid, signal.SIGKILL)
    except OSError:   # nothing left
        pass


def _die_with_parent():
    """Runs in the child before exec: get SIGTERM if the supervisor dies, whatever killed it."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass
    os.setpgrp()  # own process group: a terminal's Ctrl-C reaches the supervisor, which stops us in order


def renice(pid: int, nice: int) -> int:
    """Set the niceness of every thread of process ``pid`` (Linux niceness is per thread, and threads
    created later inherit their creator's); returns how many threads were changed. Lowering the priority
    of one's own children needs no privilege."""
    changed = 0
    for _ in range(2):   # a thread started while the first pass ran is caught by the second
        try:
            tids = [int(t.name) for t in (Path("/proc") / str(pid) / "task").iterdir()]
        except OSError:
            return changed
        for tid in tids:
            try:
                if os.getpriority(os.PRIO_PROCESS, tid) != nice:
                    os.setpriority(os.PRIO_PROCESS, tid, nice)
                    changed += 1
            except OSError:   # the thread ended meanwhile
                pass
    return changed


@dataclass
class Child:
    spec: ServiceSpec
    argv: list[str]
    log_path: Path
    cwd: Path = ROOT
    proc: subprocess.Popen | None = None
    restarts: int = 0
    state: str = "pending"  # pending, running, backoff, finished, failed, gave-up, stopped
    exit_codes: list[int] = field(default_factory=list)
    next_start: float = 0.0
    started_at: float = 0.0
    alive_token: bool = False
    token_lost_at: float | None = None
    last_heartbeat: dict = field(default_factory=dict)
    reniced: bool = False
    error: str = ""         # the last line the service wrote before it failed for good
    watchdog: Watchdog | None = None

    def start(self, env: dict) -> None:
        with open(self.log_path, "ab") as logf:
            logf.write(f"\n=== start #{self.restarts + 1} at {time.strftime('%H:%M:%S')}: {' '.join(self.argv)}\n".encode())
            # FLYSLAM_RESTARTS: how many times this service was restarted in this run (0: a fresh start);
            # a restarted service continues the run's output, a fresh one never takes an old run's.
            self.proc = subprocess.Popen(self.argv, stdout=logf, stderr=subprocess.STDOUT,
                                         env=dict(env, FLYSLAM_RESTARTS=str(self.restarts)),
                                         preexec_fn=_die_with_parent, cwd=self.cwd if self.cwd.is_dir() else ROOT)
        if self.watchdog is not None:
            self.watchdog.watch(self.proc.pid)   # setpgrp in the child: its pgid is its pid
        self.state, self.started_at = "running", time.monotonic()
        self.token_lost_at = None
        self.reniced = False

    def renice_when_up(self) -> None:
        """Apply the spec's niceness once the service is up (called when its liveliness token appears)."""
        if self.spec.nice and not self.reniced and self.proc is not None and self.proc.poll() is None:
            renice(self.proc.pid, self.spec.nice)
            self.reniced = True

    def reaped(self) -> None:
        """The service's process has exited: kill what is left of its group (grandchildren)."""
        kill_group(self.proc.pid)
        if self.watchdog is not None:
            self.watchdog.forget(self.proc.pid)

    def terminate(self, timeout: float) -> int | None:
        if self.proc is None or self.proc.poll() is not None:
            return None if self.proc is None else self.proc.returncode
        self.proc.send_signal(signal.SIGTERM)
        try:
            rc = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            log.warning("%s did not stop within %.0f s, killing it", self.spec.name, timeout)
            self.proc.kill()
            rc = self.proc.wait()
        self.reaped()
        return rc


def _invocation_folder() -> Path:
    """The folder `flyslam run` was started from, or the repository's when that folder is gone."""
    try:
        return Path.cwd()
    except OSError:
        log.warning("the current folder no longer exists: services run in %s", ROOT)
        return ROOT


class Supervisor:
    def __init__(self, launch: LaunchFile, out: Path, bus_opts, duration_s: float | None, cwd: Path | None = None):
        self.launch, self.out, self.bus_opts = launch, out, bus_opts
        # Services run where `flyslam run` was typed, so a relative path given to the launch (--var
        # recording=k00.mcap) means what the user meant; -P keeps that folder off their sys.path, so a
        # package of the user's named like one of flyslam's does not shadow it (flyslam comes from PYTHONPATH).
        self.cwd = cwd if cwd is not None else _invocation_folder()
        self.duration_s = launch.duration_s if duration_s is None else duration_s
        self.children: list[Child] = []
        self.failed_required: list[str] = []
        self.stop_reason = ""
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.watchdog: Watchdog | None = None
        self.state = "starting"
        self._record_written = 0.0

    @property
    def record_path(self) -> Path:
        return self.out / "run.json"

    def write_record(self) -> None:
        """(Re)write run.json atomically: readable whenever the supervisor dies."""
        tmp = self.record_path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(self.summary(), indent=2, default=str))
        os.replace(tmp, self.record_path)
        self._record_written = time.monotonic()

    def _substitute(self, arg: str) -> str:
        base = {"out": self.out, "root": ROOT, "recordings": ROOT / "recordings"}
        variables = {k: v.format(**base) for k, v in self.launch.vars.items()}
        return arg.format(**variables, **base)

    def prepare(self) -> None:
        (self.out / "logs").mkdir(parents=True, exist_ok=True)
        bus_argv = self.bus_opts.to_argv()
        for spec in self.launch.services:
            try:
                args = [self._substitute(a) for a in spec.args]
            except (KeyError, IndexError) as e:
                raise LaunchError(f"{self.launch.path}: {spec.name}: unknown placeholder {e} in args") from None
            argv = [sys.executable, "-P", "-m", spec.module, *args, *bus_argv]
            self.children.append(Child(spec, argv, self.out / "logs" / f"{spec.name}.log", self.cwd))
        config = {"launch": str(self.launch.path), "duration_s": self.duration_s, "out": str(self.out),
                  "bus": asdict(self.bus_opts),
                  "services": [{**asdict(c.spec), "argv": c.argv} for c in self.children]}
        (self.out / "run_config.json").write_text(json.dumps(config, indent=2))
        self.write_record()

    def _wait_until_up(self, started: list[Child], name: str) -> None:
        """Block until every running service of ``started`` has its liveliness token, at most the longest
        of their liveliness timeouts (past it the watch restarts them as hung anyway), or a stop."""
        deadline = time.monotonic() + max((c.spec.liveliness_timeout_s for c in started), default=0.0)
        t0 = time.monotonic()
        while not self._stop.is_set():
            with self._lock:
                waiting = [c.spec.name for c in started if not c.alive_token
                           and c.proc is not None and c.proc.poll() is None]
            if not waiting:
                log.info("starting %s: the services before it are up after %.1f s", name, time.monotonic() - t0)
                return
            if time.monotonic() >= deadline:
                log.warning("starting %s although %s %s not up after %.0f s", name, ", ".join(waiting),
                            "is" if len(waiting) == 1 else "are", time.monotonic() - t0)
                return
            self._stop.wait(0.05)

    # ------------------------------------------------------------------------------- bus watch
    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._lock:
            for c in self.children:
                if c.spec.name == name:
                    alive = sample.kind == zenoh.SampleKind.PUT
                    c.alive_token = alive
                    c.token_lost_at = None if alive else time.monotonic()
                    if alive:
                        c.renice_when_up()

    def _on_status(self, sample: zenoh.Sample) -> None:
        try:
            hb = decode(sample.payload.to_bytes(), Heartbeat)
        except DecodeError:
            return
        with self._lock:
            for c in self.children:
                if c.spec.name == hb.service:
                    c.last_heartbeat = {"progress": hb.progress, "rates": hb.rates, "counters": hb.counters}

    # ----------------------------------------------------------------------------------- loop
    def request_stop(self, reason: str) -> None:
        if not self._stop.is_set():
            self.stop_reason = reason
            self._stop.set()

    def run(self, node: Node) -> int:
        robot = node.robot
        node.session.liveliness().declare_subscriber(f"{robot}/health/*", self._on_liveliness, history=True)
        node.session.declare_subscriber(f"{robot}/status/*", self._on_status)
        for stream in self.launch.latch:
            node.hold_latched(stream)
        env = dict(os.environ, PYTHONUNBUFFERED="1", FLYSLAM_RUN_DIR=str(self.out))
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
        report = [sys.executable, "-c", REPORT_SOURCE, str(self.out)] if self.launch.report == "pipeline" else None
        self.watchdog = Watchdog(self.record_path, self.out / "logs" / "watchdog.log", after=report, env=env)
        self.state = "running"
        try:
            t_start = time.monotonic()
            for i, c in enumerate(self.children):
                if self._stop.is_set():
                    break
                if c.spec.wait_for_ready:
                    self._wait_until_up(self.children[:i], c.spec.name)
                log.info("starting %s", c.spec.name)
                c.watchdog = self.watchdog
                c.start(env)
                self.write_record()
                if c.spec.start_delay_s:
                    self._stop.wait(c.spec.start_delay_s)
            while not self._stop.wait(0.1):
                node.progress += 1
                if self.duration_s and time.monotonic() - t_start >= self.duration_s:
                    self.request_stop(f"duration of {self.duration_s:g} s reached")
                    break
                if self._tick(env) or time.monotonic() - self._record_written > 2.0:
                    self.write_record()
        finally:
            self.shutdown()
            self.state = "finished"
            self.write_record()
            self.watchdog.close()
        return 1 if self.failed_required else 0

    def _tick(self, env: dict) -> bool:
        """One supervision step; True when a service changed state (run.json is then rewritten)."""
        now = time.monotonic()
        changed = False
        for c in self.children:
            if c.state == "running":
                rc = c.proc.poll()
                if rc is None:
                    self._check_liveliness(c, now)
                    continue
                c.exit_codes.append(rc)
                c.reaped()
                self._on_exit(c, rc, now)
                changed = True
            elif c.state == "backoff" and now >= c.next_start:
                c.restarts += 1
                log.info("restarting %s (restart %d of %d)", c.spec.name, c.restarts, c.spec.max_restarts)
                c.start(env)
                changed = True
        return changed

    def _check_liveliness(self, c: Child, now: float) -> None:
        timeout = c.spec.liveliness_timeout_s
        if timeout <= 0:
            return
        with self._lock:
            missing_since = c.token_lost_at if c.token_lost_at is not None else (None if c.alive_token else c.started_at)
        if missing_since is not None and now - missing_since > timeout:
            log.warning("%s has had no liveliness token for %.0f s while its process runs: killing it as hung",
                        c.spec.name, now - missing_since)
            c.proc.kill()

    def _on_exit(self, c: Child, rc: int, now: float) -> None:
        spec = c.spec
        if self._stop.is_set():
            c.state = "stopped"
            return
        if rc == 0 and spec.restart != "always":
            c.state = "finished"
            log.info("%s finished", spec.name)
            if spec.ends_run:
                self.request_stop(f"{spec.name} finished")
            return
        how = f"exited with status {rc}" if rc >= 0 else f"was killed by signal {-rc}"
        bad_input = rc == BAD_INPUT_STATUS
        if spec.restart == "never" or c.restarts >= spec.max_restarts or bad_input:
            c.state = "gave-up" if spec.restart != "never" and not bad_input else "failed"
            c.error = last_line(c.log_path)
            why = ("no restarts allowed" if spec.restart == "never" else
                   "a bad file or flag, not restarted (it would fail the same way)" if bad_input else
                   f"gave up after {c.restarts} restarts")
            log.error("%s %s; %s%s", spec.name, how, why, f": {c.error}" if c.error else "")
            if spec.required:
                self.failed_required.append(spec.name)
                self.request_stop(f"required service {spec.name} failed")
            return
        delay = min(spec.backoff_s * (2 ** c.restarts), 30.0)
        log.warning("%s %s; restarting in %.1f s (see %s)", spec.name, how, delay, c.log_path)
        c.state, c.next_start = "backoff", now + delay

    def shutdown(self) -> None:
        log.info("stopping (%s)", self.stop_reason or "requested")
        for c in reversed(self.children):
            if c.proc is not None and c.state == "running":
                if c.proc.poll() is None:
                    rc = c.terminate(c.spec.stop_timeout_s)
                else:   # exited since the last tick
                    rc = c.proc.returncode
                    c.reaped()
                c.exit_codes.append(rc)
                c.state = "stopped"
            elif c.state in ("backoff", "pending"):
                c.state = "stopped"

    def summary(self) -> dict:
        with self._lock:
            services = {c.spec.name: {"state": c.state, "restarts": c.restarts, "exit_codes": list(c.exit_codes),
                                      **({"error": c.error} if c.error else {}),
                                      "pid": c.proc.pid if c.proc is not None else None,
                                      "log": str(c.log_path), **c.last_heartbeat}
                        for c in self.children}
        return {"state": self.state, "supervisor_pid": os.getpid(), "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                "stop_reason": self.stop_reason, "failed_required": self.failed_required, "services": services}


def last_line(path: Path, tail_bytes: int = 4096) -> str:
    """The last non-empty line of a log file ('' when there is none): a failed flyslam command's
    one-line error."""
    try:
        with open(path, "rb") as f:
            f.seek(max(0, f.seek(0, os.SEEK_END) - tail_bytes))
            lines = [ln.strip() for ln in f.read().decode(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    return lines[-1][:300] if lines else ""


def format_summary(summary: dict) -> str:
    lines = [f"run stopped: {summary['stop_reason']}", "",
             f"  {'service':<12} {'state':<9} {'restarts':>8} {'progress':>9}  exit codes"]
    for name, s in summary["services"].items():
        lines.append(f"  {name:<12} {s['state']:<9} {s['restarts']:>8} {s.get('progress', '-'):>9}  "
                     f"{','.join(str(x) for x in s['exit_codes']) or '-'}")
    if summary["failed_required"]:
        lines.append(f"\nFAILED: required service(s) gave up: {', '.join(summary['failed_required'])}")
        lines += [f"  {name}: {summary['services'][name]['error']}" for name in summary["failed_required"]
                  if summary["services"].get(name, {}).get("error")]
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="flyslam run", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("launch", nargs="?", default=str(DEFAULT_LAUNCH), help="launch file (TOML)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds (0 = run until Ctrl-C); default: the launch file's")
    p.add_argument("--out", default=None, help="folder for everything the run writes (default: runs/<date-time> in the current folder)")
    p.add_argument("--var", action="append", default=[], metavar="NAME=VALUE",
                   help="set a launch-file variable used as {NAME} in service args")
    p.add_argument("--viewer", action="store_true",
                   help="serve the live Rerun viewer (sets grpc_port=9876 and web_port=9090 for the bridge; "
                        "open http://127.0.0.1:9090)")
    add_bus_arguments(p)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    setup_logging("supervisor")
    try:
        launch = load_launch(Path(args.launch))
    except LaunchError as e:
        print(f"flyslam run: {e}", file=sys.stderr)
        return 2
    if args.viewer:
        launch.vars.update(grpc_port="9876", web_port="9090")
    for item in args.var:
        name, sep, value = item.partition("=")
        if not sep:
            print(f"flyslam run: --var expects NAME=VALUE, got {item!r}", file=sys.stderr)
            return 2
        launch.vars[name] = value
    here = _invocation_folder()
    out = here / (args.out or Path("runs") / time.strftime("%Y%m%d-%H%M%S"))
    opts = bus_options(args)
    if launch.robot and args.robot == "rig":
        opts.robot = launch.robot
    try:
        # a bad bus flag fails here (the config is built first), before the run folder is made
        taken = services_alive(opts)
    except BusConfigError as e:
        print(f"flyslam run: {e}", file=sys.stderr)
        return 2
    if taken:
        print(f"flyslam run: another run's services ({', '.join(taken)}) are on this bus as robot "
              f"'{opts.robot}': stop that run, or give this one its own --hub tcp/127.0.0.1:PORT or --robot NAME",
              file=sys.stderr)
        return 2
    sup = Supervisor(launch, out.resolve(), opts, args.duration, cwd=here)
    try:
        sup.prepare()
    except LaunchError as e:
        print(f"flyslam run: {e}", file=sys.stderr)
        return 2
    with Node("supervisor", opts, handle_signals=False) as node:
        def on_signal(signum, _frame):
            sup.request_stop(f"signal {signal.Signals(signum).name}")
        signal.signal(signal.SIGINT, on_signal)
        signal.signal(signal.SIGTERM, on_signal)
        status = sup.run(node)
    summary = sup.summary()
    print(format_summary(summary))
    if launch.report == "pipeline":
        from deploy.report import format_pipeline_summary, pipeline_summary
        pipeline = pipeline_summary(out)
        (out / "summary.json").write_text(json.dumps(pipeline, indent=2))
        print(format_pipeline_summary(pipeline))
    print(f"\noutput: {out}")
    return status


if __name__ == "__main__":
    sys.exit(main())
