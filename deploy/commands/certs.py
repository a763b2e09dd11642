"""`flyslam certs --out DIR --host robot=robot.local,10.0.0.5 --host laptop`: a CA and per-host certificates
for deploy/zenoh/secured.json5 (mutual TLS; the certificate's common name is the host's name, which the
access control of secured.json5 matches: only the host named ``robot`` may publish commands).

Writes DIR/ca.pem and DIR/ca-key.pem (keep the CA key off the robots), and per host DIR/NAME/ holding
ca.pem, host-cert.pem and host-key.pem: copy that folder to /etc/flyslam/tls on the host. A host's
names after ``=`` (DNS names or IP addresses) go into its certificate's subjectAltName with NAME itself;
peers connecting to it must use one of them. Uses the ``cryptography`` package when installed, else the
openssl binary. Refuses to overwrite an existing CA (exit 2) unless ``--force``.
"""
from __future__ import annotations

import argparse
import datetime
import ipaddress
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

CA_DAYS, HOST_DAYS = 3650, 825
HOST_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9.-]{0,62}$")


class CertError(ValueError):
    """A bad host specification, an existing CA, or a failed certificate tool."""


def parse_host(spec: str) -> tuple[str, list[str]]:
    """'robot=robot.local,10.0.0.5' -> ('robot', ['robot', 'robot.local', '10.0.0.5'])."""
    name, _, rest = spec.partition("=")
    names = [name] + [n for n in rest.split(",") if n]
    for n in names:
        if not (HOST_NAME.match(n) or _is_ip(n)):
            raise CertError(f"--host {spec!r}: {n!r} is not a host name or an IP address")
    return name, list(dict.fromkeys(names))


def _is_ip(text: str) -> bool:
    try:
        ipaddress.ip_address(text)
        return True
    except ValueError:
        return False


# ------------------------------------------------------------------------------- openssl backend


def _openssl(*args: str) -> None:
    exe = shutil.which("openssl")
    if exe is None:
        raise CertError("neither the 'cryptography' package nor the openssl binary is available")
    done = subprocess.run([exe, *args], capture_output=True, text=True)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no message"])[-1]
        raise CertError(f"openssl {args[0]} failed: {last}")


def _openssl_ca(key: Path, cert: Path) -> None:
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
             "-keyout", str(key), "-out", str(cert), "-days", str(CA_DAYS), "-subj", "/CN=flyslam CA",
             "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign")


def _openssl_host(ca_key: Path, ca_cert: Path, name: str, sans: list[str], key: Path, cert: Path) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        csr, ext = Path(tmp) / "host.csr", Path(tmp) / "ext.cnf"
        alt = ",".join(f"IP:{n}" if _is_ip(n) else f"DNS:{n}" for n in sans)
        ext.write_text(f"subjectAltName={alt}\nbasicConstraints=critical,CA:FALSE\n"
                       "keyUsage=critical,digitalSignature\nextendedKeyUsage=serverAuth,clientAuth\n")
        _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
                 "-keyout", str(key), "-out", str(csr), "-subj", f"/CN={name}")
        _openssl("x509", "-req", "-in", str(csr), "-CA", str(ca_cert), "-CAkey", str(ca_key), "-set_serial",
                 str(int.from_bytes(os.urandom(8), "big")), "-days", str(HOST_DAYS),
                 "-extfile", str(ext), "-out", str(cert))


# -------------------------------------------------------------------------- cryptography backend


def _crypto_ca(key_path: Path, cert_path: Path) -> None:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "flyslam CA")])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now)
            .not_valid_after(now + datetime.timedelta(days=CA_DAYS))
            .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True)
            .sign(key, hashes.SHA256()))
    key_path.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def _crypto_host(ca_key_path: Path, ca_cert_path: Path, name: str, sans: list[str], key_path: Path,
                 cert_path: Path) -> None:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    ca_key = serialization.load_pem_private_key(ca_key_path.read_bytes(), None)
    ca = x509.load_pem_x509_certificate(ca_cert_path.read_bytes())
    key = ec.generate_private_key(ec.SECP256R1())
    alt = [x509.IPAddress(ipaddress.ip_address(n)) if _is_ip(n) else x509.DNSName(n) for n in sans]
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
            .issuer_name(ca.subject).public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now).not_valid_after(now + datetime.timedelta(days=HOST_DAYS))
            .add_extension(x509.SubjectAlternativeName(alt), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .sign(ca_key, hashes.SHA256()))
    key_path.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def _backend():
    try:
        import cryptography  # noqa: F401
        return _crypto_ca, _crypto_host
    except ImportError:
        return _openssl_ca, _openssl_host


# ------------------------------------------------------------------------------------------ main


def make_certs(out: Path, hosts: list[str], force: bool = False) -> list[Path]:
    """Create (or reuse) the CA in ``out`` and one folder per host; returns the host folders."""
    specs = [parse_host(h) for h in hosts]
    make_ca, make_host = _backend()
    if out.exists() and not out.is_dir():
        raise CertError(f"--out {out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    ca_key, ca_cert = out / "ca-key.pem", out / "ca.pem"
    if ca_cert.exists() and not force:
        raise CertError(f"{ca_cert} exists: remove it or pass --force (a new CA invalidates every host's certificate)")
    make_ca(ca_key, ca_cert)
    ca_key.chmod(0o600)
    folders = []
    for name, sans in specs:
        folder = out / name
        folder.mkdir(exist_ok=True)
        make_host(ca_key, ca_cert, name, sans, folder / "host-key.pem", folder / "host-cert.pem")
        (folder / "host-key.pem").chmod(0o600)
        shutil.copyfile(ca_cert, folder / "ca.pem")
        folders.append(folder)
    return folders


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="flyslam certs", description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, type=Path, help="folder for the CA and one sub-folder per host")
    p.add_argument("--host", action="append", default=None, metavar="NAME[=DNS|IP,...]",
                   help="a host to certify (repeatable; default: robot); NAME is its certificate's common name")
    p.add_argument("--force", action="store_true", help="replace an existing CA in --out")
    args = p.parse_args(argv)
    try:
        folders = make_certs(args.out, args.host or ["robot"], args.force)
    except (CertError, OSError) as e:
        print(f"flyslam certs: {e}", file=sys.stderr)
        return 2
    for folder in folders:
        print(f"{folder}: copy to /etc/flyslam/tls on host {folder.name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
