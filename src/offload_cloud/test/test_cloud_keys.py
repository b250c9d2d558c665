"""keys.py and auth.py: CURVE key files (secret files 600, loose ones refused, one clear line for a bad
one), the allowlist reloaded on SIGHUP revoking and admitting, robots added by name."""
import os
import pathlib
import signal
import stat
import subprocess
import sys
import time

import pytest

from offload_cloud import keys
from offload_cloud.client import CloudClient, CloudTimeout
from offload_cloud.keys import load_client_keys

from cloud_test_helpers import (LOOPBACK, free_port, spawn_server, stop_process)

pytestmark = pytest.mark.timeout(180)


def _answers(key_dir, endpoint, timeout_s=1.0) -> bool:
    with CloudClient(endpoint, keys_dir=str(key_dir), timeout_s=timeout_s, retries=0) as client:
        try:
            client.ping()
            return True
        except CloudTimeout:
            return False


def test_sighup_reloads_the_allowlist_revoking_and_admitting(key_root, tmp_path):
    server_keys = key_root / "server"
    port = free_port()
    process = spawn_server(port, server_keys, log_path=tmp_path / "server.log")
    endpoint = f"{LOOPBACK}:{port}"
    try:
        revoked = CloudClient(endpoint, keys_dir=str(key_root / "robot2"), timeout_s=1.0, retries=0)
        assert revoked.ping() > 0          # connected and served before the revocation
        (server_keys / "clients" / "robot2.key").unlink()
        keys.generate(key_root, ["robot3"], add_to=server_keys)
        process.send_signal(signal.SIGHUP)
        deadline = time.monotonic() + 10
        while not _answers(key_root / "robot3", endpoint) and time.monotonic() < deadline:
            pass
        assert _answers(key_root / "robot3", endpoint), "an admitted robot is refused after SIGHUP"
        with pytest.raises(CloudTimeout):
            revoked.ping()                 # its open connection was closed, its key is refused
        revoked.close()
        assert not _answers(key_root / "robot2", endpoint)
        assert _answers(key_root / "robot", endpoint)
        # A bad allowlist on reload keeps the previous one and the server running.
        (server_keys / "clients" / "junk.key").write_text("not a key\n")
        process.send_signal(signal.SIGHUP)
        time.sleep(0.5)
        assert process.poll() is None and _answers(key_root / "robot3", endpoint)
    finally:
        stop_process(process)
    log = (tmp_path / "server.log").read_text()
    assert "allowlist reloaded" in log and "allowlist NOT reloaded" in log and "junk.key" in log
    assert "refused a CURVE handshake from 127.0.0.1" in log     # refusals at WARNING, with the address


def _strip_secret(path: pathlib.Path) -> None:
    path.write_text("".join(line for line in path.read_text().splitlines(True) if "secret-key" not in line))


def test_key_file_without_secret_fails_fast_with_one_line(key_root):
    robot_secret = key_root / "robot" / keys.CLIENT_SECRET
    _strip_secret(robot_secret)
    started = time.monotonic()
    check = subprocess.run([sys.executable, "-m", "offload_cloud.client", "tcp://127.0.0.1:9", "--ping",
                            "--keys-dir", str(key_root / "robot"), "--timeout", "1"],
                           capture_output=True, text=True, timeout=60)
    assert check.returncode == 2 and time.monotonic() - started < 30
    assert check.stderr.count("\n") == 1 and str(robot_secret) in check.stderr and "Traceback" not in check.stderr
    server_secret = key_root / "server" / keys.SERVER_SECRET
    _strip_secret(server_secret)
    server = subprocess.run([sys.executable, "-m", "offload_cloud", "--bind",
                             f"{LOOPBACK}:{free_port()}", "--keys-dir", str(key_root / "server")],
                            capture_output=True, text=True, timeout=60)
    assert server.returncode == 2 and "Traceback" not in server.stderr
    assert server.stderr.count("\n") == 1 and str(server_secret) in server.stderr
    with pytest.raises(ValueError, match=str(robot_secret)):
        CloudClient("tcp://127.0.0.1:9", keys_dir=str(key_root / "robot"))


def test_add_to_refuses_an_admitted_name_and_names_that_are_not_file_names(key_root):
    server_keys = key_root / "server"
    before = (server_keys / "clients" / "robot.key").read_bytes()
    other = key_root / "elsewhere"
    with pytest.raises(FileExistsError, match="already admitted"):
        keys.generate(other, ["robot"], add_to=server_keys)
    assert (server_keys / "clients" / "robot.key").read_bytes() == before and not (other / "robot").exists()
    assert keys.main([str(other), "--clients", "robot", "--add-to", str(server_keys)]) == 1
    keys.generate(other, ["robot"], add_to=server_keys, replace=True)
    assert (server_keys / "clients" / "robot.key").read_bytes() != before
    for name in ("..", ".", "a/b", "", "server", "clients", "-x", "x" * 65):
        with pytest.raises(ValueError, match="bad client name"):
            keys.generate(other, [name], add_to=server_keys)
    assert not (key_root / "client.key").exists() and not (key_root.parent / "client.key_secret").exists()


def test_secret_files_are_600_even_under_umask_000_and_loose_ones_are_refused(tmp_path):
    old_umask = os.umask(0)
    try:
        server_keys = keys.generate(tmp_path, ["robot"])
    finally:
        os.umask(old_umask)
    for secret in (server_keys / keys.SERVER_SECRET, tmp_path / "robot" / keys.CLIENT_SECRET):
        assert stat.S_IMODE(secret.stat().st_mode) == 0o600
    assert not stat.S_IMODE((server_keys / "clients").stat().st_mode) & 0o022
    os.chmod(tmp_path / "robot" / keys.CLIENT_SECRET, 0o644)
    with pytest.raises(keys.KeyFileError, match="readable by others"):
        load_client_keys(tmp_path / "robot")
    os.chmod(server_keys / keys.SERVER_SECRET, 0o640)
    with pytest.raises(keys.KeyFileError, match="readable by others"):
        keys.load_server_keys(server_keys)
    os.chmod(server_keys / keys.SERVER_SECRET, 0o600)
    os.chmod(server_keys / "clients", 0o777)
    with pytest.raises(keys.KeyFileError, match="writable by others"):
        keys.load_server_keys(server_keys)
    os.chmod(server_keys / "clients", 0o755)
    os.chmod(server_keys / "clients" / "robot.key", 0o666)
    with pytest.raises(keys.KeyFileError, match="writable by others"):
        keys.load_server_keys(server_keys)


def test_garbage_key_in_the_allowlist_stops_the_server_at_start_up(key_root):
    junk = key_root / "server" / "clients" / "junk.key"
    junk.write_text("garbage\n")
    server = subprocess.run([sys.executable, "-m", "offload_cloud", "--bind",
                             f"{LOOPBACK}:{free_port()}", "--keys-dir", str(key_root / "server")],
                            capture_output=True, text=True, timeout=60)
    assert server.returncode == 2 and str(junk) in server.stderr and "Traceback" not in server.stderr
