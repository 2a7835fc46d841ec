"""ZeroMQ CURVE keys for the pose stream: who may subscribe when it is bound beyond the loopback interface.

The key files are pyzmq's (``zmq.auth``): ``NAME.key`` holds a public key, ``NAME.key_secret`` the pair.
The publisher holds the server's pair and a folder of the public keys of the subscribers it lets in; each
subscriber holds its own pair and the server's public key. ``edgecal keys`` makes pairs. The check of each
subscriber's key is pyzmq's ZAP authenticator; nothing of the protocol is written here.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import zmq.auth

from edgecal.errors import InputError, exception_summary
from edgecal.fileio import check_outputs, make_folders, permission_denied

PUBLIC_SUFFIX = ".key"
SECRET_SUFFIX = ".key_secret"


@dataclass(frozen=True)
class ServerKeys:
    """What a CURVE publisher needs: its key pair and the allowed subscribers' public keys (Z85 text)."""

    public: bytes
    secret: bytes
    clients: frozenset[bytes]
    clients_dir: str


@dataclass(frozen=True)
class ClientKeys:
    """What a CURVE subscriber needs: its key pair and the publisher's public key (Z85 text)."""

    public: bytes
    secret: bytes
    server_public: bytes


def read_key_file(path: str | Path, need_secret: bool) -> tuple[bytes, bytes | None]:
    """(public, secret) of a pyzmq key file; InputError naming the file when it is not one (or, with
    ``need_secret``, holds no secret key)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: key file not found (`edgecal keys` makes key pairs)")
    try:
        public, secret = zmq.auth.load_certificate(p)
    except PermissionError:
        raise permission_denied(p, "key file") from None
    except Exception as exc:  # noqa: BLE001 - pyzmq raises ValueError, OSError or a decode error for a bad file
        raise InputError(f"{p}: not a ZeroMQ key file ({exception_summary(exc)})") from None
    if need_secret and not secret:
        raise InputError(f"{p}: holds only a public key; give the {SECRET_SUFFIX} file of the pair")
    return public, secret


def load_server_keys(secret_file: str | Path, clients_dir: str | Path) -> ServerKeys:
    """The publisher's pair and every ``*.key`` public key in ``clients_dir`` (at least one)."""
    public, secret = read_key_file(secret_file, need_secret=True)
    folder = Path(clients_dir)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder of subscribers' public keys (*{PUBLIC_SUFFIX})")
    clients = frozenset(read_key_file(f, need_secret=False)[0] for f in sorted(folder.glob(f"*{PUBLIC_SUFFIX}")))
    if not clients:
        raise InputError(f"{folder}: holds no *{PUBLIC_SUFFIX} public key; copy each subscriber's NAME.key there")
    assert secret is not None
    return ServerKeys(public, secret, clients, str(folder))


def load_client_keys(secret_file: str | Path, server_public_file: str | Path) -> ClientKeys:
    """A subscriber's pair and the publisher's public key."""
    public, secret = read_key_file(secret_file, need_secret=True)
    server_public, _ = read_key_file(server_public_file, need_secret=False)
    assert secret is not None
    return ClientKeys(public, secret, server_public)


def make_key_pair(folder: str | Path, name: str, force: bool = False) -> tuple[Path, Path]:
    """Write NAME.key (public) and NAME.key_secret (the pair, readable by its owner only) into ``folder``."""
    out = Path(folder)
    public, secret = out / f"{name}{PUBLIC_SUFFIX}", out / f"{name}{SECRET_SUFFIX}"
    check_outputs([public, secret], force, create_folders=True)
    make_folders(out)
    old = os.umask(0o077)          # the secret file is never readable by others, not even for a moment
    try:
        zmq.auth.create_certificates(out, name)
    finally:
        os.umask(old)
    os.chmod(public, 0o644 & ~old)
    return public, secret


class AllowedKeys:
    """pyzmq's ZAP credentials provider: a subscriber is let in when its public key is in the set."""

    def __init__(self, keys: frozenset[bytes]) -> None:
        self.keys = keys

    def callback(self, domain: str, key: bytes) -> bool:
        """Called by zmq.auth for every CURVE handshake (``key`` in Z85)."""
        return key in self.keys
