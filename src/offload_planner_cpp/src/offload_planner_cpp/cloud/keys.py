"""CURVE key pairs for the cloud link.

    python -m offload_planner_cpp.cloud.keys OUT_DIR --clients robot1 [robot2 ...]

writes
    OUT_DIR/server/server.key, server.key_secret     the server's pair
    OUT_DIR/server/clients/robot1.key                 the allowlist: public keys of admitted robots
    OUT_DIR/robot1/client.key, client.key_secret      robot1's pair
    OUT_DIR/robot1/server.key                         the server's public key, to authenticate it
Copy OUT_DIR/server to the cloud host (`--keys-dir`) and OUT_DIR/robot1 to robot1 (`~keys_dir`).
`--add-to SERVER_DIR` adds new robots to an existing server's allowlist instead of making a server pair.
Secret files are created readable by their owner only.
"""
import argparse
import os
import pathlib
import shutil
import sys
from typing import Tuple

import zmq.auth

SERVER_SECRET = "server.key_secret"
SERVER_PUBLIC = "server.key"
CLIENT_SECRET = "client.key_secret"
CLIENTS_DIR = "clients"


def _create_pair(directory: pathlib.Path, name: str) -> None:
    directory.mkdir(parents=True, exist_ok=True)
    zmq.auth.create_certificates(str(directory), name)
    os.chmod(directory / f"{name}.key_secret", 0o600)


def generate(out_dir, clients, add_to=None) -> pathlib.Path:
    """Creates the server pair (unless `add_to` names an existing server directory) and one pair per client
    name; returns the server directory."""
    out_dir = pathlib.Path(out_dir)
    server_dir = pathlib.Path(add_to) if add_to else out_dir / "server"
    if add_to:
        if not (server_dir / SERVER_PUBLIC).is_file():
            raise FileNotFoundError(f"{server_dir / SERVER_PUBLIC} not found: is {server_dir} a server keys dir?")
    else:
        if (server_dir / SERVER_SECRET).exists():
            raise FileExistsError(f"{server_dir} already holds a server key: use --add-to {server_dir}")
        _create_pair(server_dir, "server")
    (server_dir / CLIENTS_DIR).mkdir(exist_ok=True)
    for name in clients:
        if not name or "/" in name or name in ("server", CLIENTS_DIR):
            raise ValueError(f"bad client name {name!r}")
        client_dir = out_dir / name
        if (client_dir / CLIENT_SECRET).exists():
            raise FileExistsError(f"{client_dir} already holds a client key")
        _create_pair(client_dir, "client")
        shutil.copy(client_dir / "client.key", server_dir / CLIENTS_DIR / f"{name}.key")
        shutil.copy(server_dir / SERVER_PUBLIC, client_dir / SERVER_PUBLIC)
    return server_dir


def load_server_keys(keys_dir) -> Tuple[bytes, bytes, pathlib.Path]:
    """(public, secret, allowlist directory) of a server keys dir, with a clear error when incomplete."""
    keys_dir = pathlib.Path(keys_dir)
    secret_file = keys_dir / SERVER_SECRET
    if not secret_file.is_file():
        raise FileNotFoundError(f"{secret_file} not found: generate keys with "
                                f"`python -m offload_planner_cpp.cloud.keys OUT_DIR --clients NAME`")
    public, secret = zmq.auth.load_certificate(str(secret_file))
    clients = keys_dir / CLIENTS_DIR
    if not clients.is_dir():
        raise FileNotFoundError(f"{clients} (the client allowlist) not found")
    return public, secret, clients


def load_client_keys(keys_dir) -> Tuple[bytes, bytes, bytes]:
    """(client public, client secret, server public) of a client keys dir."""
    keys_dir = pathlib.Path(keys_dir)
    for name in (CLIENT_SECRET, SERVER_PUBLIC):
        if not (keys_dir / name).is_file():
            raise FileNotFoundError(f"{keys_dir / name} not found: copy the robot's directory made by "
                                    f"`python -m offload_planner_cpp.cloud.keys`")
    public, secret = zmq.auth.load_certificate(str(keys_dir / CLIENT_SECRET))
    server_public, _ = zmq.auth.load_certificate(str(keys_dir / SERVER_PUBLIC))
    return public, secret, server_public


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out_dir", help="directory to write the key directories into")
    parser.add_argument("--clients", nargs="+", default=["robot"], help="client (robot) names (default: robot)")
    parser.add_argument("--add-to", metavar="SERVER_DIR", help="add clients to this existing server keys dir")
    args = parser.parse_args(argv)
    try:
        server_dir = generate(args.out_dir, args.clients, args.add_to)
    except (OSError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    print(f"server keys dir: {server_dir} (copy to the cloud host, pass as --keys-dir)")
    for name in args.clients:
        print(f"client keys dir: {pathlib.Path(args.out_dir) / name} (copy to robot {name!r}, bridge ~keys_dir)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
