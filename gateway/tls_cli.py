"""``psgateway tls init DIR``: the certificates of a first TLS set-up, and the lines that use them.

One run writes a CA, a server certificate for this machine (and the names given with ``--host``)
and a client certificate per ``--client NAME`` (subject CN = NAME, the identity the access rules
see), then prints the gateway's ``[tls]`` section and the psctl and grpcurl flags for each client.
It writes nothing when any of its files is already there, unless ``--force``.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from typing import Any

from gateway.certificates import DEFAULT_SERVER_NAMES, issue_certificate, make_authority, write_private_key

__all__ = ["add_parser"]

#: Exit code of a run that wrote nothing: files in the way, or a bad name.
EXIT_REFUSED = 2
#: A client's name becomes a file name and the certificate's subject: no path separators, no spaces.
_CLIENT_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
#: File stems of the CA and the server, which no client may take.
_RESERVED = ("ca", "server")

EXAMPLES = """\
examples:
  psgateway tls init certs --client operator --client viewer
  psgateway tls init certs --host gw.example --host 10.0.0.5 --client operator
  psgateway tls init certs --force              make a new set in place of the old one
"""


def add_parser(subparsers: Any) -> None:
    """Add the ``tls`` subcommand (``tls init``) to ``subparsers``."""
    tls: argparse.ArgumentParser = subparsers.add_parser(
        "tls",
        help="make certificates for TLS and mutual TLS",
        description="Certificates for the gateway's TLS (docs/security.md).",
    )
    actions = tls.add_subparsers(title="actions", metavar="ACTION", required=True)
    init = actions.add_parser(
        "init",
        help="make a CA, a server certificate and client certificates in DIR",
        description="Make a CA (ca.pem, ca.key), a server certificate (server.pem, server.key) for "
        f"{', '.join(DEFAULT_SERVER_NAMES)} and each --host, and a client certificate per --client "
        "(NAME.pem, NAME.key) in DIR, as PEM files (private keys mode 0600); then print the config "
        "lines and client flags that use them.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    init.add_argument("dir", metavar="DIR", help="folder for the files (created if missing)")
    init.add_argument(
        "--host",
        action="append",
        default=[],
        metavar="NAME",
        help="another DNS name or IP address the server certificate is valid for (repeatable)",
    )
    init.add_argument(
        "--client",
        action="append",
        default=[],
        metavar="NAME",
        help="a client certificate with subject CN=NAME, written as NAME.pem and NAME.key (repeatable);"
        " with any, the printed config requires client certificates (mutual TLS)",
    )
    init.add_argument(
        "--days", type=_days, default=365, metavar="N", help="days the certificates are valid (default: 365)"
    )
    init.add_argument("--force", action="store_true", help="replace files that are already there")
    init.set_defaults(func=_init)


def _days(text: str) -> int:
    try:
        days = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number of days, got {text!r}") from None
    if days < 1:
        raise argparse.ArgumentTypeError(f"expected at least 1 day, got {text!r}")
    return days


def _refuse(message: str) -> int:
    print(f"psgateway: tls init: {message}", file=sys.stderr)
    return EXIT_REFUSED


def _init(args: argparse.Namespace) -> int:
    clients: list[str] = list(dict.fromkeys(args.client))
    for name in clients:
        if not _CLIENT_NAME.match(name):
            return _refuse(f"bad client name {name!r}: use letters, digits, '.', '_' and '-'")
        if name in _RESERVED:
            return _refuse(f"the client name {name!r} is taken by the {name} files; choose another")
    folder = Path(args.dir).resolve()
    if folder.exists() and not folder.is_dir():
        return _refuse(f"{folder} is not a folder")
    stems = [*_RESERVED, *clients]
    files = [folder / f"{stem}.{suffix}" for stem in stems for suffix in ("pem", "key")]
    in_the_way = [str(path) for path in files if path.exists()]
    if in_the_way and not args.force:
        return _refuse(
            f"not replacing {', '.join(in_the_way)} (give --force to make a new set in their place)"
        )
    hosts = list(dict.fromkeys([*DEFAULT_SERVER_NAMES, *args.host]))
    # The first name given is the one clients are shown dialling; on this machine, localhost.
    main_name = args.host[0] if args.host else "localhost"
    folder.mkdir(parents=True, exist_ok=True)
    authority = make_authority(folder, "ca", days=args.days)
    write_private_key(authority.private_key, folder / "ca.key")
    server = issue_certificate(
        authority, folder, "server", main_name, server=True, hosts=hosts, days=args.days
    )
    pairs = {name: issue_certificate(authority, folder, name, name, days=args.days) for name in clients}
    rows = [
        ("ca.pem, ca.key", "the CA (keep ca.key off the gateway: whoever has it can sign certificates)"),
        ("server.pem, server.key", f"the gateway's certificate, for {', '.join(hosts)}"),
        *((f"{name}.pem, {name}.key", f"a client certificate, subject CN={name}") for name in clients),
    ]
    width = max(len(names) for names, _ in rows)
    print(f"wrote in {folder}:")
    for names, what in rows:
        print(f"  {names.ljust(width)}  {what}")
    print("\nthe gateway's config file (docs/security.md):\n")
    print("[tls]")
    print(f'cert = "{server.cert}"')
    print(f'key = "{server.key}"')
    ca = authority.cert_path
    if pairs:
        print(f'client_ca = "{ca}"')
        print("require_client_cert = true")
    address = f"{main_name}:50051"
    if not pairs:
        print("\nclients:\n")
        print(f"  psctl -t {address} --ca {ca} ls")
        print(f"  grpcurl -cacert {ca} {address} list")
    for name, pair in pairs.items():
        print(f"\nclient {name}:\n")
        print(f"  psctl -t {address} --ca {ca} --cert {pair.cert} --key {pair.key} ls")
        print(f"  PSCTL_CA={ca} PSCTL_CERT={pair.cert} PSCTL_KEY={pair.key} psctl -t {address} ls")
        print(f"  grpcurl -cacert {ca} -cert {pair.cert} -key {pair.key} {address} list")
    return 0
