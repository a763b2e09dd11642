"""The secured deployment of bench/faults.py: the demo under `flyslam run --config` (deploy/zenoh/secured.json5
with certificates from `flyslam certs`), and attackers in another network namespace.

The robot's side listens on one end of a veth pair (``ip netns``: a second host without a second
machine); each attacker runs in the namespace at the other end and sends ``count`` velocity commands
and targets: over plain TCP with no credentials, over TLS with no client certificate, with a
certificate of a rogue CA whose common name is "robot", and with a valid certificate of another host
(the laptop), whose config drops the access control (an attacker chooses its own configuration).
An observer with the robot's certificate counts what a robot process accepts: ``attacker_commands_delivered``
(attackers' commands heard), ``secured_poses`` (slam/pose messages), and ``attacker_heard_on_allowed_keys``
(the laptop's status messages: the attackers did reach the robot). Where ``ip netns`` is not permitted
the attack is skipped with the reason, and the pipeline runs on loopback.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
SECURED = ROOT / "deploy" / "zenoh" / "secured.json5"
ATTACK_X = 77.0          # the attackers' target, recognisable on the robot's side
ATTACK_REASON = "attacker"


class Netns:
    """A network namespace joined to this one by a veth pair: ``robot_ip`` here, ``attacker_ip`` there."""

    def __init__(self):
        tag = os.getpid() % 100000
        self.name, self.here, self.there = f"flyslam-atk-{tag}", f"fsa{tag}", f"fsb{tag}"
        net = f"10.213.{tag % 250}"
        self.robot_ip, self.attacker_ip = f"{net}.1", f"{net}.2"
        self.sudo = [] if os.geteuid() == 0 else ["sudo", "-n"]

    def unavailable(self) -> str | None:
        """Why ``ip netns`` cannot be used here, or None."""
        if not shutil.which("ip"):
            return "no 'ip' command (iproute2)"
        if self.sudo and subprocess.run(["sudo", "-n", "true"], capture_output=True).returncode != 0:
            return "not root and 'sudo -n' is not permitted"
        done = subprocess.run([*self.sudo, "ip", "netns", "add", self.name], capture_output=True, text=True)
        if done.returncode != 0:
            return f"'ip netns add' refused: {done.stderr.strip() or done.returncode}"
        return None

    def setup(self) -> None:
        ns = [*self.sudo, "ip", "netns", "exec", self.name]
        for cmd in ([*self.sudo, "ip", "link", "add", self.here, "type", "veth", "peer", "name", self.there],
                    [*self.sudo, "ip", "link", "set", self.there, "netns", self.name],
                    [*self.sudo, "ip", "addr", "add", f"{self.robot_ip}/30", "dev", self.here],
                    [*self.sudo, "ip", "link", "set", self.here, "up"],
                    [*ns, "ip", "addr", "add", f"{self.attacker_ip}/30", "dev", self.there],
                    [*ns, "ip", "link", "set", self.there, "up"],
                    [*ns, "ip", "link", "set", "lo", "up"]):
            subprocess.run(cmd, check=True, capture_output=True)

    def exec_argv(self, argv: list[str]) -> list[str]:
        return [*self.sudo, "ip", "netns", "exec", self.name, *argv]

    def remove(self) -> None:
        subprocess.run([*self.sudo, "ip", "netns", "del", self.name], capture_output=True)
        subprocess.run([*self.sudo, "ip", "link", "del", self.here], capture_output=True)


def host_config(tmp: Path, certs: Path, name: str, robot_ip: str, port: int, listen_ip: str,
                access_control: bool = True) -> Path:
    """secured.json5 as a host fills it in: its certificate folder, the robot's address and port, its own
    listen address (an attacker may also drop the access control)."""
    text = SECURED.read_text().replace("/etc/flyslam/tls", str(certs))
    text = text.replace("ROBOT_HOST:7447", f"{robot_ip}:{port}")
    text = text.replace("tls/0.0.0.0:7447", f"tls/{listen_ip}:{port}").replace("tls/0.0.0.0:0", f"tls/{listen_ip}:0")
    if not access_control:
        text = text.replace("enabled: true,", "enabled: false,", 1)
    path = tmp / f"{name}.json5"
    path.write_text(text)
    return path


def attacker_configs(tmp: Path, certs: Path, rogue: Path, robot_ip: str, port: int, my_ip: str) -> dict[str, Path]:
    def write(name: str, cfg: dict) -> Path:
        path = tmp / f"attacker-{name}.json5"
        path.write_text(json.dumps(cfg, indent=1))
        return path

    scouting = {"multicast": {"enabled": False}, "gossip": {"enabled": True}}
    no_cert = {"root_ca_certificate": str(certs / "ca.pem"), "verify_name_on_connect": True}
    rogue_cert = {**no_cert, "connect_private_key": str(rogue / "host-key.pem"),
                  "connect_certificate": str(rogue / "host-cert.pem"), "enable_mtls": True}
    return {
        "plain tcp, no credentials": write("tcp", {"mode": "peer", "scouting": scouting,
                                                   "connect": {"endpoints": [f"tcp/{robot_ip}:{port}"]}}),
        "tls, no client certificate": write("nocert", {"mode": "peer", "scouting": scouting,
                                                       "connect": {"endpoints": [f"tls/{robot_ip}:{port}"]},
                                                       "transport": {"link": {"tls": no_cert}}}),
        "rogue CA, CN=robot": write("rogue", {"mode": "peer", "scouting": scouting,
                                              "connect": {"endpoints": [f"tls/{robot_ip}:{port}"]},
                                              "transport": {"link": {"tls": rogue_cert}}}),
        "laptop certificate, no ACL": host_config(tmp, certs / "laptop", "attacker-laptop", robot_ip, port, my_ip,
                                                  access_control=False),
    }


def attack(config: str, count: int, robot: str = "rig") -> dict:
    """Runs in the attacker's namespace: open a session with ``config`` and send ``count`` commands and
    targets (and status messages, allowed to any certified peer); what was sent, as a dict."""
    import zenoh

    from common import messages as m
    from common.bus import BusOptions, make_config

    try:
        session = zenoh.open(make_config(BusOptions(config=config)))
    except Exception as e:  # noqa: BLE001 - a refused session is a result, not a failure
        return {"opened": False, "error": str(e).splitlines()[0] if str(e) else type(e).__name__, "sent": 0}
    sent = 0
    try:
        time.sleep(3.0)   # connect, and reach the other peers by gossip
        for i in range(count):
            stamp = time.time_ns()
            cmd = m.VelocityCommand(linear_mps=1.0, angular_radps=0.5, reason=ATTACK_REASON,
                                    header=m.header(i + 1, stamp, m.BASE_LINK))
            target = m.Target(x=ATTACK_X, y=0.0, header=m.header(i + 1, stamp, m.MAP))
            session.put(f"{robot}/planner/cmd_vel", m.encode(cmd))
            session.put(f"{robot}/planner/target", m.encode(target))
            session.put(f"{robot}/status/attacker", m.encode(m.Heartbeat(service="attacker", progress=i)))
            sent += 2
            time.sleep(0.05)
        time.sleep(1.0)
    finally:
        session.close()
    return {"opened": True, "sent": sent}


class Observer:
    """A robot-side session counting poses, attackers' commands and the laptop's status messages."""

    def __init__(self, config: Path, robot: str = "rig"):
        import zenoh

        from common import messages as m
        from common.bus import BusOptions, make_config

        self.poses = self.commands = self.heard = 0
        self.session = zenoh.open(make_config(BusOptions(config=str(config))))

        def on_pose(_sample):
            self.poses += 1

        def on_command(sample):
            try:
                msg = m.decode(sample.payload.to_bytes(), (m.VelocityCommand, m.Target))
            except m.DecodeError:
                return
            if getattr(msg, "reason", None) == ATTACK_REASON or getattr(msg, "x", None) == ATTACK_X:
                self.commands += 1

        def on_status(_sample):
            self.heard += 1

        self._subs = [self.session.declare_subscriber(f"{robot}/slam/pose", on_pose),
                      self.session.declare_subscriber(f"{robot}/planner/cmd_vel", on_command),
                      self.session.declare_subscriber(f"{robot}/planner/target", on_command),
                      self.session.declare_subscriber(f"{robot}/status/attacker", on_status)]

    def close(self) -> None:
        self._subs.clear()
        self.session.close()


def secured_run(tmp: Path, flyslam: list[str], env: dict, port: int, seconds: float, count: int = 50) -> dict:
    from deploy.commands.certs import main as certs_main

    netns = Netns()
    skipped = netns.unavailable()
    robot_ip = "127.0.0.1" if skipped else netns.robot_ip
    certs, rogue = tmp / "certs", tmp / "rogue"
    hosts = ["--host", f"robot=localhost,127.0.0.1,{robot_ip}", "--host", f"laptop={netns.attacker_ip}"]
    with open(os.devnull, "w") as quiet:
        stdout, sys.stdout = sys.stdout, quiet
        try:
            made = certs_main(["--out", str(certs), *hosts]) == 0 and \
                certs_main(["--out", str(rogue), "--host", f"robot={netns.attacker_ip}"]) == 0
        finally:
            sys.stdout = stdout
    if not made:
        raise RuntimeError("flyslam certs failed")
    robot_cfg = host_config(tmp, certs / "robot", "robot", robot_ip, port, robot_ip)
    observer_cfg = host_config(tmp, certs / "robot", "observer", robot_ip, port, robot_ip)
    result: dict = {"secured_run_s": seconds}
    attacks: dict = {}
    try:
        if not skipped:
            netns.setup()
        run = tmp / "secured"
        sup = subprocess.Popen([*flyslam, "run", str(ROOT / "deploy" / "launch" / "demo.toml"), "--config", str(robot_cfg),
                                "--out", str(run), "--duration", str(seconds)], cwd=ROOT, env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(2.0)   # the supervisor takes the well-known port first
        observer = Observer(observer_cfg)
        try:
            deadline = time.monotonic() + seconds * 0.6
            while observer.poses == 0 and time.monotonic() < deadline and sup.poll() is None:
                time.sleep(0.5)
            if skipped:
                result["attacker_skipped"] = f"ip netns not permitted: {skipped}"
            else:
                configs = attacker_configs(tmp, certs, rogue / "robot", robot_ip, port, netns.attacker_ip)
                for variant, cfg in configs.items():
                    before = observer.commands
                    done = subprocess.run(netns.exec_argv([sys.executable, str(Path(__file__)), "--attack", str(cfg),
                                                           "--count", str(count)]),
                                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
                    try:
                        report = json.loads(done.stdout.strip().splitlines()[-1])
                    except (IndexError, ValueError):
                        report = {"opened": None, "sent": 0, "error": (done.stderr.strip().splitlines() or ["?"])[-1]}
                    time.sleep(1.0)
                    attacks[variant] = {**report, "delivered": observer.commands - before}
            sup.wait(seconds + 120)
        finally:
            if sup.poll() is None:
                sup.send_signal(signal.SIGTERM)
                sup.wait(60)
            observer.close()
    finally:
        if not skipped:
            netns.remove()
    result.update({"secured_poses": observer.poses, "secured_listen": robot_ip})
    if attacks:
        result.update({"attacker_commands_sent": sum(a["sent"] for a in attacks.values()),
                       "attacker_commands_delivered": sum(a["delivered"] for a in attacks.values()),
                       "attacker_heard_on_allowed_keys": observer.heard, "attacks": attacks})
    else:
        result["attacker_commands_delivered"] = None
    return result


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="attacker process (run by secured_run inside the namespace)")
    p.add_argument("--attack", required=True, help="the attacker's Zenoh config")
    p.add_argument("--count", type=int, default=50)
    args = p.parse_args(argv)
    print(json.dumps(attack(args.attack, args.count)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
