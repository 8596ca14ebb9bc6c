"""Throwaway X.509 material for TLS tests, made with the ``openssl`` command line (P-256 keys, valid
for two days): a CA, and leaf certificates it signs (server: SAN ``localhost`` / ``127.0.0.1``;
client: subject CN = the agent id)."""

from __future__ import annotations

import secrets
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

_REQ = """[req]
distinguished_name = dn
prompt = no
[dn]
CN = {cn}
[ca_ext]
basicConstraints = critical,CA:TRUE
keyUsage = critical,keyCertSign,cRLSign
subjectKeyIdentifier = hash
[leaf_ext]
basicConstraints = critical,CA:FALSE
keyUsage = critical,digitalSignature
extendedKeyUsage = serverAuth,clientAuth
subjectAltName = DNS:localhost,IP:127.0.0.1
authorityKeyIdentifier = keyid
"""


@dataclass(frozen=True)
class Pem:
    """A certificate and its key (PEM files)."""

    cert: Path
    key: Path

    def cert_bytes(self) -> bytes:
        return self.cert.read_bytes()

    def key_bytes(self) -> bytes:
        return self.key.read_bytes()


def _openssl(*args: str, cwd: Path) -> None:
    exe = shutil.which("openssl")
    if exe is None:
        pytest.skip("openssl command line not installed")
    r = subprocess.run([exe, *args], cwd=str(cwd), capture_output=True, text=True, timeout=60)
    if r.returncode != 0:
        raise RuntimeError(f"openssl {' '.join(args[:2])} failed: {r.stderr[-1000:]}")


def make_ca(directory: Path, name: str) -> Pem:
    """A self-signed CA ``directory/<name>.pem`` / ``.key``."""
    directory.mkdir(parents=True, exist_ok=True)
    cnf = directory / f"{name}.cnf"
    cnf.write_text(_REQ.format(cn=f"GaussLite test CA {name}"))
    pem = Pem(directory / f"{name}.pem", directory / f"{name}.key")
    _openssl("req", "-x509", "-new", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
             "-keyout", str(pem.key), "-out", str(pem.cert), "-days", "2", "-config", str(cnf), "-extensions",
             "ca_ext", cwd=directory)
    return pem


def make_leaf(directory: Path, name: str, ca: Pem, cn: str) -> Pem:
    """A certificate with subject CN ``cn`` signed by ``ca`` (server and client usage, SAN localhost/127.0.0.1)."""
    directory.mkdir(parents=True, exist_ok=True)
    cnf = directory / f"{name}.cnf"
    cnf.write_text(_REQ.format(cn=cn))
    csr = directory / f"{name}.csr"
    pem = Pem(directory / f"{name}.pem", directory / f"{name}.key")
    _openssl("req", "-new", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
             "-keyout", str(pem.key), "-out", str(csr), "-config", str(cnf), cwd=directory)
    _openssl("x509", "-req", "-in", str(csr), "-CA", str(ca.cert), "-CAkey", str(ca.key), "-set_serial",
             str(secrets.randbits(63)), "-days", "2", "-out", str(pem.cert), "-extfile", str(cnf), "-extensions",
             "leaf_ext", cwd=directory)
    return pem
