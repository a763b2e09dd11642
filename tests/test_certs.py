"""flyslam certs and deploy/zenoh/secured.json5 on loopback: certificates that verify, a process that
refuses a placeholder host or a missing certificate with one line, and a mutual-TLS bus on which only
the robot's certificate may publish commands."""
from __future__ import annotations

import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh

from common.bus import BusConfigError, BusOptions, make_config
from deploy.commands.certs import main as certs_main
from tests.conftest import free_port

ROOT = Path(__file__).resolve().parents[1]
SECURED = ROOT / "deploy" / "zenoh" / "secured.json5"


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("certs")
    assert certs_main(["--out", str(out), "--host", "robot=localhost,127.0.0.1",
                       "--host", "laptop=localhost,127.0.0.1"]) == 0
    return out


def _config(tmp_path: Path, certs: Path, host: str, port: int, name: str) -> Path:
    """secured.json5 as a host would fill it in, on loopback: its certificate folder, the robot's port."""
    text = SECURED.read_text().replace("/etc/flyslam/tls", str(certs / host)).replace("ROBOT_HOST", "127.0.0.1")
    text = text.replace("tls/0.0.0.0:7447", f"tls/127.0.0.1:{port}").replace("tls/0.0.0.0:0", "tls/127.0.0.1:0")
    text = text.replace('connect: { endpoints: ["tls/127.0.0.1:7447"] }',
                        f'connect: {{ endpoints: ["tls/127.0.0.1:{port}"] }}')
    path = tmp_path / f"{name}.json5"
    path.write_text(text)
    return path


def test_certs_makes_a_ca_and_per_host_certificates_that_verify(certs):
    for host in ("robot", "laptop"):
        folder = certs / host
        assert {p.name for p in folder.iterdir()} == {"ca.pem", "host-cert.pem", "host-key.pem"}
        assert (folder / "host-key.pem").stat().st_mode & 0o077 == 0
        if shutil.which("openssl"):
            done = subprocess.run(["openssl", "verify", "-CAfile", str(certs / "ca.pem"), str(folder / "host-cert.pem")],
                                  capture_output=True, text=True)
            assert done.returncode == 0, done.stderr
            subject = subprocess.run(["openssl", "x509", "-in", str(folder / "host-cert.pem"), "-noout", "-subject"],
                                     capture_output=True, text=True).stdout
            assert f"CN = {host}" in subject or f"CN={host}" in subject


def test_certs_refuses_to_replace_a_ca_and_a_bad_host_name(certs, capsys):
    assert certs_main(["--out", str(certs)]) == 2
    assert certs_main(["--out", str(certs.parent / "other"), "--host", "robot=bad name!"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith("flyslam certs: ") for line in err)


def test_secured_config_as_shipped_or_without_certificates_is_refused_with_one_line(tmp_path, certs):
    with pytest.raises(BusConfigError, match="ROBOT_HOST placeholder"):
        make_config(BusOptions(config=str(SECURED)))
    with pytest.raises(BusConfigError, match="not found .*flyslam certs"):
        make_config(BusOptions(config=str(SECURED), connect=["tls/127.0.0.1:7447"]))
    done = subprocess.run([sys.executable, "-m", "deploy.cli", "fusion", "--config", str(SECURED)], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1 and "ROBOT_HOST" in lines[0], done.stderr


def _deliveries(tmp_path, certs, publishers: dict[str, str], keys: list[str]) -> dict[tuple[str, str], int]:
    """Open a robot listener and one session per publisher (name -> certificate host); each puts 20
    messages on every key. Returns how many the robot's subscriber received per (publisher, key)."""
    port = free_port()
    received: dict[tuple[str, str], int] = {}
    robot = zenoh.open(make_config(BusOptions(config=str(_config(tmp_path, certs, "robot", port, "robot")))))
    sessions = []
    try:
        def on_sample(sample):
            who = sample.payload.to_bytes().decode()
            received[(who, str(sample.key_expr))] = received.get((who, str(sample.key_expr)), 0) + 1

        subs = [robot.declare_subscriber(k, on_sample) for k in keys]
        for name, host in publishers.items():
            sessions.append((name, zenoh.open(make_config(BusOptions(
                config=str(_config(tmp_path, certs, host, port, name)))))))
        time.sleep(1.5)
        for name, session in sessions:
            for key in keys:
                for _ in range(20):
                    session.put(key, name.encode())
        time.sleep(1.0)
        del subs
    finally:
        for _, session in sessions:
            session.close()
        robot.close()
    return received


def test_only_the_robots_certificate_may_publish_commands(tmp_path, certs):
    keys = ["flyslam/planner/cmd_vel", "flyslam/planner/target", "flyslam/status/x"]
    got = _deliveries(tmp_path, certs, {"planner": "robot", "laptop": "laptop"}, keys)
    assert got.get(("laptop", "flyslam/status/x"), 0) == 20, got     # the laptop is connected and heard...
    assert got.get(("laptop", "flyslam/planner/cmd_vel"), 0) == 0, got   # ...but cannot drive the robot
    assert got.get(("laptop", "flyslam/planner/target"), 0) == 0, got
    assert got.get(("planner", "flyslam/planner/cmd_vel"), 0) == 20, got
    assert got.get(("planner", "flyslam/planner/target"), 0) == 20, got


def test_a_peer_with_a_certificate_from_another_ca_is_not_heard(tmp_path, certs):
    rogue = tmp_path / "rogue"
    assert certs_main(["--out", str(rogue), "--host", "robot=localhost,127.0.0.1"]) == 0
    merged = tmp_path / "merged"
    shutil.copytree(certs, merged)
    shutil.rmtree(merged / "rogue-robot", ignore_errors=True)
    shutil.copytree(rogue / "robot", merged / "rogue-robot")
    got = _deliveries(tmp_path, merged, {"rogue": "rogue-robot"}, ["flyslam/planner/cmd_vel", "flyslam/status/x"])
    assert sum(got.values()) == 0, got


def test_every_peer_listens_so_two_late_peers_hear_each_other_directly(tmp_path, certs):
    """The first process takes the well-known port; two later ones (connected only to it) must still
    reach each other: in peer mode the first does not forward between them."""
    port = free_port()
    first = zenoh.open(make_config(BusOptions(config=str(_config(tmp_path, certs, "robot", port, "first")))))
    b = zenoh.open(make_config(BusOptions(config=str(_config(tmp_path, certs, "robot", port, "b")))))
    c = zenoh.open(make_config(BusOptions(config=str(_config(tmp_path, certs, "laptop", port, "c")))))
    try:
        heard = []
        sub = c.declare_subscriber("flyslam/fusion/pose", lambda s: heard.append(s.payload.to_bytes()))
        deadline = time.monotonic() + 10
        while not heard and time.monotonic() < deadline:
            b.put("flyslam/fusion/pose", b"pose")
            time.sleep(0.2)
        del sub
        assert heard, "a late peer's data did not reach another late peer"
        first.close()                        # without the first process, b and c still talk
        heard.clear()
        deadline = time.monotonic() + 5
        sub = c.declare_subscriber("flyslam/fusion/pose", lambda s: heard.append(s.payload.to_bytes()))
        while not heard and time.monotonic() < deadline:
            b.put("flyslam/fusion/pose", b"pose")
            time.sleep(0.2)
        assert heard, "late peers lost each other when the first process ended"
    finally:
        for s in (b, c):
            s.close()


def test_every_stream_of_the_pipeline_passes_the_secured_bus(tmp_path, certs):
    """A stream the access rules forget is silently lost (the localiser once took a verbatim '@' key,
    which no wildcard rule covers)."""
    from common import streams as S
    commands = {S.PLANNER_CMD_VEL.key, S.PLANNER_TARGET.key}          # the robot's certificate only: above
    keys = [f"flyslam/{s.key}" for s in vars(S).values()
            if isinstance(s, S.Stream) and "*" not in s.key and s.key not in commands]
    got = _deliveries(tmp_path, certs, {"laptop": "laptop"}, keys)
    assert {k: got.get(("laptop", k), 0) for k in keys} == {k: 20 for k in keys}
