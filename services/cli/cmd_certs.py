"""``gausslite certs``: the team's TLS material and robot credentials in one command (``docs/security.md``).

    gausslite certs provision --dir ~/gausslite-secrets agent_a agent_b report   # CA, server and robot certificates
                                                                                  # + robot tokens and the token file
    gausslite certs issue agent_a --dir ~/gausslite-secrets          # renew one robot's certificate (same CA)
    gausslite certs show agent_a.pem                                 # CN, issuer, expiry, SHA-256 fingerprint

``provision`` writes into DIR: ``ca.pem``/``ca.key`` (the CA; kept when present), ``server.pem``/``server.key`` (parser
and fusion servers; SANs from ``--server-name``), ``<agent>.pem``/``<agent>.key`` per agent (CN = agent id, short-lived:
``--days``), and, unless ``--no-tokens``, ``<agent>.token`` plus the fusion server's ``fusion_tokens.json``
(``gausslite tokens provision``). Keys and tokens are mode 0600. Existing files are kept unless ``--force``. Exit
status 0 on success, 2 on bad input.
"""

from __future__ import annotations

import argparse
import sys


def register(subparsers) -> None:
    """Add the ``certs`` subcommand to ``subparsers`` (imports nothing of the services: the library's CLI registers
    it without gRPC)."""

    p = subparsers.add_parser("certs", help="CA, certificates and tokens for the services and robots (TLS)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="certs_cmd", metavar="ACTION")
    sub.required = True
    v = sub.add_parser("provision", help="CA, server certificate, one certificate and token per agent, token file")
    v.add_argument("agent_ids", nargs="+", help="agent ids (robots, and clients such as a report job)")
    v.add_argument("--dir", required=True, help="output folder (keep it out of the repository and the images)")
    v.add_argument("--server-name", action="append", default=None, metavar="NAME",
                   help="DNS name or IP the parser/fusion servers are dialled by (repeatable; default: the service "
                        "names of deploy/, localhost and 127.0.0.1: "
                        "gausslite_services.common.pki.DEFAULT_SERVER_NAMES)")
    v.add_argument("--days", type=int, default=90, help="validity of the robots' certificates (default 90)")
    v.add_argument("--server-days", type=int, default=365, help="validity of the server certificate (default 365)")
    v.add_argument("--no-tokens", action="store_true", help="certificates only (no bearer tokens)")
    v.add_argument("--force", action="store_true", help="replace existing certificates and tokens (the CA is kept)")
    i = sub.add_parser("issue", help="a new certificate for one agent from the CA in --dir (renewal)")
    i.add_argument("agent_id")
    i.add_argument("--dir", required=True, help="folder with ca.pem and ca.key")
    i.add_argument("--days", type=int, default=90)
    s = sub.add_parser("show", help="subject, issuer, expiry and fingerprint of a certificate")
    s.add_argument("certificate")
    p.set_defaults(func=_handle)


def _handle(args: argparse.Namespace) -> int:
    # lazy: the command line starts without loading the services or gRPC
    from pathlib import Path

    from gausslite_services.common import auth, pki

    try:
        if args.certs_cmd == "provision":
            names = tuple(args.server_name) if args.server_name else pki.DEFAULT_SERVER_NAMES
            made = pki.provision_pki(args.dir, args.agent_ids, server_names=names, days=args.days,
                                     server_days=args.server_days, force=args.force)
            for what, path in made.items():
                print(f"{what}: " + (f"new certificate {path}" if path else "kept (--force replaces it)"))
            if not args.no_tokens:
                for agent, path in auth.provision(args.dir, args.agent_ids, force=args.force).items():
                    print(f"{agent}: " + (f"new token in {path}" if path else "token kept"))
                print(f"token hashes in {Path(args.dir) / 'fusion_tokens.json'}")
        elif args.certs_cmd == "issue":
            d = Path(args.dir)
            cert, _ = pki.issue_certificate(d / "ca.pem", d / "ca.key", d / f"{args.agent_id}.pem",
                                            d / f"{args.agent_id}.key", args.agent_id,
                                            server_names=[args.agent_id, "localhost", "127.0.0.1"], server=True,
                                            days=args.days)
            info = pki.certificate_info(cert)
            print(f"{args.agent_id}: new certificate {cert}, valid until {info['not_after']}")
        else:
            info = pki.certificate_info(args.certificate)
            print(f"subject CN: {info['subject_cn']}\nissuer CN:  {info['issuer_cn']}\nvalid until: {info['not_after']}"
                  f"\nnames:      {', '.join(info['names']) or '-'}\nsha256:     {info['fingerprint']}")
    except (ValueError, OSError, RuntimeError) as e:
        print(f"gausslite certs: error: {e}", file=sys.stderr)
        return 2
    return 0
