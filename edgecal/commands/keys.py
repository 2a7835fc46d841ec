"""``edgecal keys FOLDER --name NAME``: make a ZeroMQ CURVE key pair for the pose stream.

A pose stream bound beyond the loopback interface (``publish.allow_remote: true``) lets in only
subscribers whose public key it holds. Make one pair for the publisher and one per subscriber::

    edgecal keys /etc/edgecal/keys --name server        # publish.curve.server_key: server.key_secret
    edgecal keys ~/.edgecal --name laptop               # on the subscriber's machine
    cp laptop.key /etc/edgecal/keys/clients/            # publish.curve.client_keys: the allowed subscribers
    edgecal listen tcp://robot:5560 --key ~/.edgecal/laptop.key_secret --server-key server.key

NAME.key is the public key (give it away); NAME.key_secret holds the pair and is readable by its owner only.
"""

from __future__ import annotations

import argparse

from edgecal.errors import InputError, quote
from edgecal.publish.curve import make_key_pair


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``edgecal keys``."""
    p = subparsers.add_parser("keys", help="make a CURVE key pair for a remote pose stream or subscriber",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folder", help="where to write NAME.key and NAME.key_secret (created if missing)")
    p.add_argument("--name", default="server", help="file name of the pair (default: server)")
    p.add_argument("--force", action="store_true", help="replace an existing pair of that name")
    return p


def run(args: argparse.Namespace) -> int:
    """Write the pair; print where it is."""
    if not args.name or "/" in args.name or args.name.startswith("."):
        raise InputError(f"--name {quote(args.name)}: a plain file name, e.g. server or laptop")
    public, secret = make_key_pair(args.folder, args.name, force=args.force)
    print(f"public key {public} (give it away)\nsecret key {secret} (keep it; readable by you only)")
    return 0
