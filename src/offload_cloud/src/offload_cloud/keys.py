"""CURVE key pairs for the cloud link.

    python -m offload_cloud.keys OUT_DIR --clients robot1 [robot2 ...]

writes
    OUT_DIR/server/server.key, server.key_secret     the server's pair
    OUT_DIR/server/clients/robot1.key                 the allowlist: public keys of admitted robots
    OUT_DIR/robot1/client.key, client.key_secret      robot1's pair
    OUT_DIR/robot1/server.key                         the server's public key, to authenticate it
Copy OUT_DIR/server to the cloud host (`--keys-dir`) and OUT_DIR/robot1 to robot1 (`~keys_dir`).
`--add-to SERVER_DIR` adds new robots to an existing server's allowlist instead of making a server pair.
Secret files are created readable by their owner only (mode 600 from the start, whatever the umask), and
a secret file readable by others is refused when loaded. `--add-to` refuses a name already admitted
unless `--replace`. The server reloads its allowlist on SIGHUP.
"""
import argparse
import os
import pathlib
import re
import shutil
import stat
import struct
import sys
import tempfile
from typing import FrozenSet, Optional, Tuple

import zmq.auth
from zmq.utils import z85

SERVER_SECRET = "server.key_secret"
SERVER_PUBLIC = "server.key"
CLIENT_SECRET = "client.key_secret"
CLIENT_PUBLIC = "client.key"
CLIENTS_DIR = "clients"
# A key file is about 300 bytes; anything much larger is not one and is not read.
MAX_KEY_FILE_BYTES = 4096
_CLIENT_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


class KeyFileError(ValueError):
    """A key file or directory that cannot be used; the message names it and says what to do."""


def _create_pair(directory: pathlib.Path, name: str) -> None:
    """Writes name.key and name.key_secret into `directory`; the secret is mode 600 from the moment it
    exists (written in a private 700 temporary directory, then moved), whatever the umask."""
    directory.mkdir(parents=True, exist_ok=True)
    staging = pathlib.Path(tempfile.mkdtemp(prefix=".keys-", dir=directory))
    try:
        zmq.auth.create_certificates(str(staging), name)
        os.chmod(staging / f"{name}.key_secret", 0o600)
        os.chmod(staging / f"{name}.key", 0o644)
        os.replace(staging / f"{name}.key_secret", directory / f"{name}.key_secret")
        os.replace(staging / f"{name}.key", directory / f"{name}.key")
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def check_client_name(name: str) -> str:
    if not _CLIENT_NAME.fullmatch(name or "") or name in ("server", CLIENTS_DIR):
        raise ValueError(f"bad client name {name!r}: use 1-64 letters, digits, '_', '-' or '.', starting with "
                         f"a letter or digit (not 'server' or 'clients')")
    return name


def generate(out_dir, clients, add_to=None, replace: bool = False) -> pathlib.Path:
    """Creates the server pair (unless `add_to` names an existing server directory) and one pair per client
    name; returns the server directory. An allowlisted name is refused unless `replace`."""
    out_dir = pathlib.Path(out_dir)
    for name in clients:
        check_client_name(name)
    if len(set(clients)) != len(clients):
        raise ValueError(f"client names repeat: {' '.join(clients)}")
    server_dir = pathlib.Path(add_to) if add_to else out_dir / "server"
    if add_to:
        if not (server_dir / SERVER_PUBLIC).is_file():
            raise FileNotFoundError(f"{server_dir / SERVER_PUBLIC} not found: is {server_dir} a server keys dir?")
    else:
        if (server_dir / SERVER_SECRET).exists():
            raise FileExistsError(f"{server_dir} already holds a server key: use --add-to {server_dir}")
    for name in clients:   # every check before anything is written
        if (server_dir / CLIENTS_DIR / f"{name}.key").exists() and not replace:
            raise FileExistsError(f"{server_dir / CLIENTS_DIR / (name + '.key')} exists: robot {name!r} is already "
                                  f"admitted (pass --replace to give it a new key and lock out the old one)")
        if (out_dir / name / CLIENT_SECRET).exists() and not replace:
            raise FileExistsError(f"{out_dir / name} already holds a client key (pass --replace to overwrite)")
    if not add_to:
        server_dir.mkdir(parents=True, exist_ok=True)
        os.chmod(server_dir, 0o700)
        _create_pair(server_dir, "server")
    (server_dir / CLIENTS_DIR).mkdir(mode=0o755, exist_ok=True)
    for name in clients:
        client_dir = out_dir / name
        client_dir.mkdir(parents=True, exist_ok=True)
        os.chmod(client_dir, 0o700)
        _create_pair(client_dir, "client")
        shutil.copy(client_dir / CLIENT_PUBLIC, server_dir / CLIENTS_DIR / f"{name}.key")
        os.chmod(server_dir / CLIENTS_DIR / f"{name}.key", 0o644)
        shutil.copy(server_dir / SERVER_PUBLIC, client_dir / SERVER_PUBLIC)
        os.chmod(client_dir / SERVER_PUBLIC, 0o644)
    return server_dir


def _check_not_writable_by_others(path: pathlib.Path, mode: int) -> None:
    if mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise KeyFileError(f"{path} is writable by others (mode {stat.S_IMODE(mode):04o}): anyone could replace "
                           f"keys; run chmod go-w {path}")


def read_key_file(path, need_secret: bool) -> Tuple[bytes, Optional[bytes]]:
    """(public, secret) of one key file, checked: size, format, both keys 32 bytes, and for a secret file
    mode 600 (not readable by others). KeyFileError naming the file otherwise."""
    path = pathlib.Path(path)
    try:
        info = path.stat()
    except FileNotFoundError:
        raise
    except OSError as error:
        raise KeyFileError(f"{path}: cannot read: {error.strerror}") from None
    if not stat.S_ISREG(info.st_mode):
        raise KeyFileError(f"{path} is not a regular file")
    if info.st_size > MAX_KEY_FILE_BYTES:
        raise KeyFileError(f"{path} is {info.st_size} bytes: not a key file (at most {MAX_KEY_FILE_BYTES})")
    _check_not_writable_by_others(path, info.st_mode)
    if need_secret and info.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise KeyFileError(f"{path} holds a secret key but is readable by others (mode "
                           f"{stat.S_IMODE(info.st_mode):04o}): run chmod 600 {path}, and make new keys if "
                           f"others may have read it")
    try:
        public, secret = zmq.auth.load_certificate(str(path))
    except (ValueError, UnicodeDecodeError, IndexError) as error:
        raise KeyFileError(f"{path} is not a ZeroMQ key file ({error})") from None
    except OSError as error:
        raise KeyFileError(f"{path}: cannot read: {error.strerror}") from None
    for label, key in (("public-key", public), ("secret-key", secret)):
        if key is None:
            if label == "secret-key" and not need_secret:
                continue
            raise KeyFileError(f"{path} has no {label} line: not a complete "
                               f"{'secret ' if need_secret else ''}key file; make new keys with "
                               f"`python -m offload_cloud.keys`")
        if len(key) != 40 or _z85_bytes(key) is None:
            raise KeyFileError(f"{path}: its {label} is not a 40-character Z85 key")
    return public, secret


def _z85_bytes(key: bytes) -> Optional[bytes]:
    try:
        decoded = z85.decode(key)
    except (ValueError, KeyError, TypeError, IndexError, struct.error):
        return None
    return decoded if len(decoded) == 32 else None


def load_allowlist(clients_dir) -> FrozenSet[bytes]:
    """Z85 public keys of every `*.key` in the allowlist directory; KeyFileError naming the first bad file
    (a garbage key must stop the server at start-up, not leave it refusing every robot)."""
    clients_dir = pathlib.Path(clients_dir)
    if not clients_dir.is_dir():
        raise FileNotFoundError(f"{clients_dir} (the client allowlist) not found")
    _check_not_writable_by_others(clients_dir, clients_dir.stat().st_mode)
    keys = set()
    for path in sorted(clients_dir.glob("*.key")):
        public, _ = read_key_file(path, need_secret=False)
        keys.add(public)
    return frozenset(keys)


def load_server_keys(keys_dir) -> Tuple[bytes, bytes, pathlib.Path]:
    """(public, secret, allowlist directory) of a server keys dir, with a clear error when incomplete."""
    keys_dir = pathlib.Path(keys_dir)
    secret_file = keys_dir / SERVER_SECRET
    if not secret_file.is_file():
        raise FileNotFoundError(f"{secret_file} not found: generate keys with "
                                f"`python -m offload_cloud.keys OUT_DIR --clients NAME`")
    public, secret = read_key_file(secret_file, need_secret=True)
    clients = keys_dir / CLIENTS_DIR
    load_allowlist(clients)   # fails now on a bad key file
    return public, secret, clients


def load_client_keys(keys_dir) -> Tuple[bytes, bytes, bytes]:
    """(client public, client secret, server public) of a client keys dir."""
    keys_dir = pathlib.Path(keys_dir)
    for name in (CLIENT_SECRET, SERVER_PUBLIC):
        if not (keys_dir / name).is_file():
            raise FileNotFoundError(f"{keys_dir / name} not found: copy the robot's directory made by "
                                    f"`python -m offload_cloud.keys`")
    public, secret = read_key_file(keys_dir / CLIENT_SECRET, need_secret=True)
    server_public, _ = read_key_file(keys_dir / SERVER_PUBLIC, need_secret=False)
    return public, secret, server_public


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out_dir", help="directory to write the key directories into")
    parser.add_argument("--clients", nargs="+", default=["robot"], help="client (robot) names (default: robot)")
    parser.add_argument("--add-to", metavar="SERVER_DIR", help="add clients to this existing server keys dir")
    parser.add_argument("--replace", action="store_true",
                        help="give robots that are already admitted a new key (their old key stops working)")
    args = parser.parse_args(argv)
    try:
        server_dir = generate(args.out_dir, args.clients, args.add_to, args.replace)
    except (OSError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    print(f"server keys dir: {server_dir} (copy to the cloud host, pass as --keys-dir)")
    for name in args.clients:
        print(f"client keys dir: {pathlib.Path(args.out_dir) / name} (copy to robot {name!r}, bridge ~keys_dir)")
    if args.add_to:
        print("send the server SIGHUP to admit the new robots without a restart")
    return 0


if __name__ == "__main__":
    sys.exit(main())
