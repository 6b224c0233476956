"""``wavegrasp keys [--out keys] [--host NAME ...]``: this installation's logins and certificates.

Access control on the bus (``ops/zenoh/acl/router.json5``: who may publish what) needs a
password per login and, on links that leave the computer (the tether), certificates for mutual
TLS. None is in the repository: this makes them, once per installation, into ``--out``
(default ``keys/``, which git ignores; readable by its owner and its group only):

- ``credentials.txt``: one ``login:password`` a line (random, 32 characters), the router's;
- ``<process>.json5``: each process's zenoh config, its login (the sim logs in as ``arm``,
  as a real arm's driver does) and its TLS client certificate, for
  ``ZENOH_CONFIG='keys/{service}.json5'``; ``router.json5``: the access-control rules of
  ``ops/zenoh/acl/router.json5``, this folder's credentials and the router's TLS listener
  (used on a ``tls/`` endpoint: ``ZENOH_LISTEN=tcp/127.0.0.1:7447,tls/0.0.0.0:7448``);
- ``ca.pem`` and ``ca-key.pem``: a certificate authority of this installation's own (ten
  years), which signed ``router-cert.pem`` (valid for ``localhost``, ``127.0.0.1``,
  ``router`` and every ``--host``) and each login's client certificate
  (``<login>-cert.pem``, its common name the login: an access-control subject).

Paths inside the files are absolute, as ``--out`` is named (in a container, as the container
sees it). A folder that holds keys already is kept (exit 0, one line saying so) unless
``--force``. Exit code 2 for a folder that cannot be written.
"""

from __future__ import annotations

import argparse
import datetime
import ipaddress
import json
import os
import re
import secrets
import sys
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from wavegrasp.ops.sample import project_root

#: Every process that opens a session, and the login it uses (the sim is the arm).
LOGINS = {"router": None, "recorder": "recorder", "perception": "perception",
          "predictor": "predictor", "planner": "planner", "gate": "gate", "sim": "arm",
          "player": "player", "edge": "edge", "foxglove": "foxglove",
          "scene": "scene", "launcher": "launcher",
          "health-check": "health-check"}
#: The login a router presents to another (the rules let it pass on what its own admitted).
ROUTER_LOGIN = "router"
RULES = Path("ops") / "zenoh" / "acl" / "router.json5"
VALID_DAYS = 3650


def new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def subject(name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name),
                      x509.NameAttribute(NameOID.ORGANIZATION_NAME, "wavegrasp")])


def certificate(name: str, key: ec.EllipticCurvePrivateKey, issuer: x509.Name,
                signer: ec.EllipticCurvePrivateKey, *, ca: bool = False,
                hosts: list[str] | None = None, client: bool = False) -> x509.Certificate:
    """A certificate for ``name`` (its common name), signed by ``signer``: a CA's, a server's
    valid for ``hosts`` (names or addresses), or a client's."""
    now = datetime.datetime.now(datetime.timezone.utc)
    build = (x509.CertificateBuilder().subject_name(subject(name)).issuer_name(issuer)
             .public_key(key.public_key()).serial_number(x509.random_serial_number())
             .not_valid_before(now - datetime.timedelta(minutes=5))
             .not_valid_after(now + datetime.timedelta(days=VALID_DAYS))
             .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True))
    if ca:
        build = build.add_extension(x509.KeyUsage(
            digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
            key_encipherment=False, data_encipherment=False, key_agreement=False,
            encipher_only=False, decipher_only=False), critical=True)
    else:  # a router's serves its listeners and is presented on its links to other routers
        usages = [ExtendedKeyUsageOID.CLIENT_AUTH] if client else [
            ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
        build = build.add_extension(x509.ExtendedKeyUsage(usages), critical=False)
    if hosts:
        names: list[x509.GeneralName] = []
        for host in hosts:
            try:
                names.append(x509.IPAddress(ipaddress.ip_address(host)))
            except ValueError:
                names.append(x509.DNSName(host))
        build = build.add_extension(x509.SubjectAlternativeName(names), critical=False)
    return build.sign(signer, hashes.SHA256())


def pem_key(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def pem_cert(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def router_config(rules: str, out: Path, password: str) -> str:
    """The router's config: the access-control rules file ``rules`` (JSON5 text) with this
    folder's credentials, the router's TLS listener, and its login and certificate for a
    link to another router (the topside's to the vehicle's, across the tether)."""
    cert, key = str(out / "router-cert.pem"), str(out / "router-key.pem")
    tls = {"root_ca_certificate": str(out / "ca.pem"), "listen_certificate": cert,
           "listen_private_key": key, "connect_certificate": cert, "connect_private_key": key,
           "enable_mtls": True, "close_link_on_expiration": True}
    login = f"user: {json.dumps(ROUTER_LOGIN)}, password: {json.dumps(password)}, "
    text, n = re.subn(r'dictionary_file:\s*"[^"]*"',
                      f"{login}dictionary_file: {json.dumps(str(out / 'credentials.txt'))}",
                      rules)
    if n != 1:
        raise ValueError(f"{RULES}: no usrpwd dictionary_file to point at the credentials")
    text, n = re.subn(r"transport:\s*\{", "transport: {\n    link: { tls: "
                      + json.dumps(tls) + " },", text, count=1)
    if n != 1:
        raise ValueError(f"{RULES}: no transport section")
    return (f"// Made by `wavegrasp keys` from {RULES}: edit the rules there and make the keys "
            f"again.\n{text}")


def client_config(login: str, password: str, out: Path) -> str:
    """A process's config: its login, and its certificate for a TLS link."""
    conf = {"transport": {
        "auth": {"usrpwd": {"user": login, "password": password}},
        "link": {"tls": {"root_ca_certificate": str(out / "ca.pem"),
                         "connect_certificate": str(out / f"{login}-cert.pem"),
                         "connect_private_key": str(out / f"{login}-key.pem"),
                         "enable_mtls": True}}}}
    return f"// {login}'s login, made by `wavegrasp keys`.\n{json.dumps(conf, indent=2)}\n"


def make_keys(out: Path, hosts: list[str]) -> list[str]:
    """Write a new set into ``out``; returns the files written."""
    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    out.chmod(0o750)
    files: dict[str, bytes] = {}
    ca_key = new_key()
    ca = certificate("wavegrasp CA", ca_key, subject("wavegrasp CA"), ca_key, ca=True)
    files["ca.pem"], files["ca-key.pem"] = pem_cert(ca), pem_key(ca_key)
    router_key = new_key()
    files["router-cert.pem"] = pem_cert(certificate(
        "router", router_key, ca.subject, ca_key,
        hosts=list(dict.fromkeys(["localhost", "127.0.0.1", "router", *hosts]))))
    files["router-key.pem"] = pem_key(router_key)
    passwords = {login: secrets.token_urlsafe(24) for login in LOGINS.values() if login}
    router_password = secrets.token_urlsafe(24)
    files["credentials.txt"] = "".join(
        f"{u}:{p}\n" for u, p in {**passwords, ROUTER_LOGIN: router_password}.items()).encode()
    for login in passwords:
        key = new_key()
        files[f"{login}-cert.pem"] = pem_cert(certificate(login, key, ca.subject, ca_key,
                                                          client=True))
        files[f"{login}-key.pem"] = pem_key(key)
    for process, login in LOGINS.items():
        if login is None:
            rules = (project_root() / RULES).read_text()
            files["router.json5"] = router_config(rules, out, router_password).encode()
        else:
            files[f"{process}.json5"] = client_config(login, passwords[login], out).encode()
    for name, data in files.items():
        path = out / name
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o640)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        path.chmod(0o640)  # the group: compose's recorder runs as the run folder's owner
    return sorted(files)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="wavegrasp keys", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("keys"),
                        help="the folder (default keys/, ignored by git)")
    parser.add_argument("--host", action="append", default=[],
                        help="a name or address the router is reached at over TLS (the "
                        "topside's on the tether); repeat for more")
    parser.add_argument("--force", action="store_true",
                        help="make a new set even where one is (every process then needs "
                        "the new files)")
    args = parser.parse_args(argv)
    if (args.out / "credentials.txt").exists() and not args.force:
        print(f"wavegrasp keys: {args.out} holds keys already: kept (--force makes new ones)",
              file=sys.stderr)
        return 0
    try:
        written = make_keys(args.out, args.host)
    except (OSError, ValueError) as exc:
        print(f"wavegrasp keys: {args.out}: {exc}", file=sys.stderr)
        return 2
    print(f"wavegrasp keys: {len(written)} files in {args.out.resolve()}: start every process "
          f"with ZENOH_CONFIG='{args.out.resolve()}/{{service}}.json5'", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
