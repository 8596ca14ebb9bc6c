"""``gausslite tokens``: per-agent bearer tokens of the fusion server (``docs/security.md``).

The server's token file stores only hashes (``agents: {agent_id: sha256:...}``); the tokens themselves
go to the robots (a docker secret, a Kubernetes Secret, a file on the robot).

    gausslite tokens issue robot-1 --tokens-file fusion_tokens.json --token-out robot-1.token
    gausslite tokens issue robot-1 --tokens-file fusion_tokens.json --keep-old   # rotation: old + new work
    gausslite tokens revoke robot-1 --tokens-file fusion_tokens.json [--keep-newest]
    gausslite tokens hash < token.txt                                             # the record of a token
    gausslite tokens provision --dir deploy/secrets agent_a agent_b report       # what docker compose mounts

The fusion server re-reads the token file when it changes (and on SIGHUP): a revoked token is refused
from the next call on. Exit status 0 on success, 1 when ``revoke`` found nothing, 2 on bad input.
"""

from __future__ import annotations

import argparse
import sys


def register(subparsers) -> None:
    """Add the ``tokens`` subcommand to ``subparsers``."""
    p = subparsers.add_parser("tokens", help="per-agent bearer tokens of the fusion server",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="tokens_cmd", metavar="ACTION")
    sub.required = True
    h = sub.add_parser("hash", help="print the at-rest record of a token (read from stdin unless --token)")
    h.add_argument("--token", default=None)
    h.add_argument("--scheme", choices=("sha256", "pbkdf2"), default="sha256",
                   help="sha256 for generated tokens, pbkdf2 for tokens a person chose")
    h.add_argument("--iterations", type=int, default=200_000, help="pbkdf2 iterations")
    i = sub.add_parser("issue", help="new random token for an agent; its hash goes into the token file")
    i.add_argument("agent_id")
    i.add_argument("--tokens-file", required=True, help="the fusion server's token file (created when missing)")
    i.add_argument("--token-out", default=None, help="write the token to this file (mode 0600) instead of stdout")
    i.add_argument("--keep-old", action="store_true", help="keep the agent's older tokens (rotation)")
    i.add_argument("--scheme", choices=("sha256", "pbkdf2"), default="sha256")
    r = sub.add_parser("revoke", help="remove an agent's tokens from the token file")
    r.add_argument("agent_id")
    r.add_argument("--tokens-file", required=True)
    r.add_argument("--keep-newest", action="store_true", help="remove all but the newest token (end of a rotation)")
    v = sub.add_parser("provision", help="DIR/<agent>.token per agent plus the token file DIR/fusion_tokens.json")
    v.add_argument("agent_ids", nargs="+")
    v.add_argument("--dir", required=True)
    v.add_argument("--tokens-name", default="fusion_tokens.json", help="token file name (.json/.yaml)")
    v.add_argument("--force", action="store_true", help="replace existing token files (old tokens stop working)")
    p.set_defaults(func=_handle)


def _handle(args: argparse.Namespace) -> int:
    # lazy: the command line starts without loading the services or gRPC
    from gausslite_services.common import auth

    try:
        if args.tokens_cmd == "hash":
            token = args.token if args.token is not None else sys.stdin.readline().strip()
            print(auth.hash_token(token, args.scheme, args.iterations))
        elif args.tokens_cmd == "issue":
            token = auth.issue_token(args.tokens_file, args.agent_id, keep_old=args.keep_old, scheme=args.scheme)
            if args.token_out:
                auth.write_secret(args.token_out, token)
                print(f"token of {args.agent_id} written to {args.token_out}; its hash is in {args.tokens_file}")
            else:
                print(token)
        elif args.tokens_cmd == "revoke":
            done = auth.revoke_token(args.tokens_file, args.agent_id, keep_newest=args.keep_newest)
            print(f"{'revoked' if done else 'nothing to revoke for'} {args.agent_id} in {args.tokens_file}")
            return 0 if done else 1
        else:
            made = auth.provision(args.dir, args.agent_ids, tokens_name=args.tokens_name, force=args.force)
            for agent, path in made.items():
                print(f"{agent}: " + (f"new token in {path}" if path else "token file exists, kept (--force replaces it)"))
            print(f"token hashes in {args.dir}/{args.tokens_name}")
    except (ValueError, OSError) as e:
        print(f"gausslite tokens: error: {e}", file=sys.stderr)
        return 2
    return 0
