"""A team's X.509 material for TLS and mutual TLS (``gausslite certs``; ``docs/security.md``), made with the
``cryptography`` package: a CA, a server certificate for the services, and one client certificate per robot whose
subject CN is its agent id (the fusion server's identity for mutual TLS).

Keys are ECDSA P-256, written unencrypted in PKCS#8 PEM with mode 0600 (gRPC reads unencrypted keys only; protect
the files); certificates are PEM. The server certificate also allows client authentication, so a service's own
health probe can present it (its CN, ``GaussLite server``, names no agent: a team member that writes nothing).

Files of :func:`provision_pki` in its directory::

    ca.pem, ca.key              the CA (keep ca.key off the robots and out of every container)
    server.pem, server.key      the parser's and fusion servers' certificate (SANs: the given server names)
    <agent>.pem, <agent>.key    one certificate per agent id (CN = agent id): its client certificate towards the
                                fusion server, and the server certificate of its own agent port
"""

from __future__ import annotations

import datetime
import ipaddress
import os
from pathlib import Path
from typing import Dict, Iterable, Optional, Sequence, Tuple

from gausslite_services.common.auth import AGENT_ID_RE

__all__ = ["SERVER_CN", "DEFAULT_SERVER_NAMES", "make_ca", "issue_certificate", "provision_pki", "certificate_info"]

#: subject CN of the server certificate: not an agent id, so a probe presenting it is a team member
SERVER_CN = "GaussLite server"
#: names the services are dialled by in deploy/ (compose service names, the replicas' alias) and locally
DEFAULT_SERVER_NAMES = ("fusion", "fusion_server", "fusion_server_2", "parser", "localhost", "127.0.0.1")


def _crypto():
    # lazy: only certificate commands load cryptography; a missing install is reported as a RuntimeError
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes, serialization
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
    except ImportError as e:  # a dependency of the package
        raise RuntimeError(f"certificates need the 'cryptography' package: {e}") from None
    return x509, hashes, serialization, ec, ExtendedKeyUsageOID, NameOID


def _write(path: Path, data: bytes, mode: int) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.chmod(tmp, mode)
    os.replace(tmp, path)


def _save(cert, key, cert_path: Path, key_path: Path) -> Tuple[Path, Path]:
    _, _, serialization, _, _, _ = _crypto()
    _write(key_path, key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                       serialization.NoEncryption()), 0o600)
    _write(cert_path, cert.public_bytes(serialization.Encoding.PEM), 0o644)
    return cert_path, key_path


def _now():
    return datetime.datetime.now(datetime.timezone.utc)


def make_ca(cert_path: str | os.PathLike, key_path: str | os.PathLike, *, common_name: str = "GaussLite team CA",
            days: int = 3650) -> Tuple[Path, Path]:
    """Make a self-signed CA (P-256, ``days`` of validity) and write it.

    Returns:
        (certificate path, key path).
    Raises:
        ValueError: ``days`` < 1. OSError: unwritable paths. RuntimeError: ``cryptography`` missing.
    """
    if int(days) < 1:
        raise ValueError("a certificate needs at least 1 day of validity")
    x509, hashes, _, ec, _, NameOID = _crypto()
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])
    ski = x509.SubjectKeyIdentifier.from_public_key(key.public_key())
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(_now() - datetime.timedelta(minutes=5))
            .not_valid_after(_now() + datetime.timedelta(days=int(days)))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                         crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(ski, critical=False)
            .sign(key, hashes.SHA256()))
    return _save(cert, key, Path(cert_path), Path(key_path))


def _load_ca(ca_cert: str | os.PathLike, ca_key: str | os.PathLike):
    x509, _, serialization, _, _, _ = _crypto()
    cert = x509.load_pem_x509_certificate(Path(ca_cert).read_bytes())
    key = serialization.load_pem_private_key(Path(ca_key).read_bytes(), password=None)
    return cert, key


def issue_certificate(ca_cert: str | os.PathLike, ca_key: str | os.PathLike, cert_path: str | os.PathLike,
                      key_path: str | os.PathLike, common_name: str, *, server_names: Iterable[str] = (),
                      server: bool = False, days: int = 90) -> Tuple[Path, Path]:
    """Issue a certificate signed by the CA (``ca_cert``/``ca_key``) with a new P-256 key, and write both.

    Args:
        common_name (str): the subject CN (a robot's agent id for a client certificate).
        server_names (Iterable[str]): DNS names and IP addresses for the subject alternative names (servers).
        server (bool): server and client authentication (else client authentication only).
        days (int): validity; short-lived client certificates limit what a stolen key is worth.
    Returns:
        (certificate path, key path).
    Raises:
        ValueError: ``days`` < 1, an empty CN. OSError: unreadable CA or unwritable paths.
    """
    if int(days) < 1:
        raise ValueError("a certificate needs at least 1 day of validity")
    if not common_name:
        raise ValueError("a certificate needs a common name")
    x509, hashes, _, ec, EKU, NameOID = _crypto()
    ca, ca_private = _load_ca(ca_cert, ca_key)
    key = ec.generate_private_key(ec.SECP256R1())
    sans = []
    for n in server_names:
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(n)))
        except ValueError:
            sans.append(x509.DNSName(n))
    b = (x509.CertificateBuilder().subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)]))
         .issuer_name(ca.subject).public_key(key.public_key()).serial_number(x509.random_serial_number())
         .not_valid_before(_now() - datetime.timedelta(minutes=5))
         .not_valid_after(min(_now() + datetime.timedelta(days=int(days)), ca.not_valid_after_utc))
         .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
         .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                      data_encipherment=False, key_agreement=False, key_cert_sign=False,
                                      crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
         .add_extension(x509.ExtendedKeyUsage([EKU.SERVER_AUTH, EKU.CLIENT_AUTH] if server else [EKU.CLIENT_AUTH]),
                        critical=False)
         .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_private.public_key()), critical=False))
    if sans:
        b = b.add_extension(x509.SubjectAlternativeName(sans), critical=False)
    return _save(b.sign(ca_private, hashes.SHA256()), key, Path(cert_path), Path(key_path))


def provision_pki(directory: str | os.PathLike, agent_ids: Sequence[str], *,
                  server_names: Iterable[str] = DEFAULT_SERVER_NAMES, days: int = 90, server_days: int = 365,
                  ca_days: int = 3650, force: bool = False) -> Dict[str, Optional[Path]]:
    """The CA (made when missing, kept otherwise), the server certificate and one client certificate per agent in
    ``directory`` (see the module docstring); existing certificates are kept unless ``force``.

    Args:
        directory: created when missing.
        agent_ids: the agents (1..64 characters of ``[A-Za-z0-9_.-]`` each). An agent's certificate also serves
            its own gRPC port (SANs: its id, ``localhost``, ``127.0.0.1``), so no robot needs the server's key.
        server_names: names and addresses the parser and fusion services are dialled by.
        days / server_days / ca_days (int): validity of the client certificates, the server certificate, the CA.
        force (bool): issue new server and client certificates even where they exist (the CA is kept).
    Returns:
        dict: ``"ca"``, ``"server"`` and each agent id → the certificate written, or None when one was kept.
    Raises:
        ValueError: a bad agent id or validity. OSError: unwritable directory.
    """
    for a in agent_ids:
        if not AGENT_ID_RE.match(a):
            raise ValueError(f"invalid agent id {a!r}: need 1..64 characters of [A-Za-z0-9_.-]")
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    ca_cert, ca_key = out / "ca.pem", out / "ca.key"
    done: Dict[str, Optional[Path]] = {"ca": None, "server": None}
    if not (ca_cert.exists() and ca_key.exists()):
        done["ca"] = make_ca(ca_cert, ca_key, days=ca_days)[0]
        force = True  # certificates of another CA would not verify
    names = list(dict.fromkeys(server_names))
    if force or not (out / "server.pem").exists():
        done["server"] = issue_certificate(ca_cert, ca_key, out / "server.pem", out / "server.key", SERVER_CN,
                                           server_names=names, server=True, days=server_days)[0]
    for a in agent_ids:
        cert = out / f"{a}.pem"
        done[a] = None
        if force or not cert.exists():
            # a robot's certificate also serves its own agent port (its name is a SAN), so it allows both uses
            done[a] = issue_certificate(ca_cert, ca_key, cert, out / f"{a}.key", a, server_names=[a, "localhost",
                                        "127.0.0.1"], server=True, days=days)[0]
    return done


def certificate_info(path: str | os.PathLike) -> dict:
    """``{"subject_cn", "issuer_cn", "not_after" (ISO 8601, UTC), "fingerprint" (SHA-256 hex), "names"}`` of a PEM
    certificate. Raises ValueError / OSError for an unreadable one."""
    x509, hashes, _, _, _, NameOID = _crypto()
    cert = x509.load_pem_x509_certificate(Path(path).read_bytes())
    cn = lambda name: ", ".join(a.value for a in name.get_attributes_for_oid(NameOID.COMMON_NAME))  # noqa: E731
    try:
        names = [str(v) for v in cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
                 .get_values_for_type(x509.DNSName)]
        names += [str(v) for v in cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
                  .get_values_for_type(x509.IPAddress)]
    except x509.ExtensionNotFound:
        names = []
    return {"subject_cn": cn(cert.subject), "issuer_cn": cn(cert.issuer),
            "not_after": cert.not_valid_after_utc.isoformat(), "fingerprint": cert.fingerprint(hashes.SHA256()).hex(),
            "names": names}
