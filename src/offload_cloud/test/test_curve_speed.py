"""curve_speed.py: the workspace's pyzmq encrypts CURVE with the system's libsodium, not the slow one a pyzmq
wheel bundles, and a server that finds the bundled one says so and how to fix it."""
import logging
import subprocess
import sys

from offload_cloud import curve_speed

from cloud_test_helpers import start_server

_WHEEL = ("7f01a0000000-7f01a0100000 r-xp 00000000 08:01 42 "
          "/venv/lib/python3.11/site-packages/pyzmq.libs/libsodium-19479d6d.so.26.2.0\n"
          "7f01a0200000-7f01a0300000 r-xp 00000000 08:01 43 "
          "/venv/lib/python3.11/site-packages/pyzmq.libs/libzmq-7b073b3d.so.5.2.5\n")
_DEBIAN = ("7f01a0000000-7f01a0100000 r-xp 00000000 08:01 44 /usr/lib/x86_64-linux-gnu/libsodium.so.23.3.0\n"
           "7f01a0200000-7f01a0300000 r-xp 00000000 08:01 45 /usr/lib/x86_64-linux-gnu/libzmq.so.5.2.4\n"
           "7f01a0400000-7f01a0500000 rw-p 00000000 00:00 0 \n")


def test_the_workspace_pyzmq_uses_the_systems_libsodium():
    # The wheel's libsodium ran crypto_box at 57 MiB/s here, Debian's at 1.3-1.5 GiB/s.
    assert not curve_speed.bundled_libsodium(), curve_speed.loaded_libraries()
    assert any("libsodium" in path for path in curve_speed.loaded_libraries())


def test_as_a_script_it_exits_0_on_the_systems_libsodium():
    # The Makefile runs it before the workspace is built, and rebuilds pyzmq when it exits 1.
    done = subprocess.run([sys.executable, curve_speed.__file__], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr


def test_the_bundled_libsodium_is_recognised_from_the_memory_map(tmp_path):
    maps = tmp_path / "maps"
    maps.write_text(_WHEEL)
    assert curve_speed.bundled_libsodium(str(maps))
    maps.write_text(_DEBIAN)
    assert not curve_speed.bundled_libsodium(str(maps))
    assert curve_speed.loaded_libraries(str(maps)) == ["/usr/lib/x86_64-linux-gnu/libsodium.so.23.3.0",
                                                       "/usr/lib/x86_64-linux-gnu/libzmq.so.5.2.4"]
    assert curve_speed.loaded_libraries(str(tmp_path / "absent")) == []


def test_a_curve_server_warns_about_the_bundled_libsodium(key_root, monkeypatch, caplog):
    for bundled in (True, False):
        monkeypatch.setattr(curve_speed, "bundled_libsodium", lambda: bundled)
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="offload_cloud.server"):
            server = start_server(key_root / "server")
            server.stop()
        warned = [record.getMessage() for record in caplog.records if "bundled in pyzmq" in record.getMessage()]
        assert len(warned) == int(bundled), warned
        if bundled:
            assert "--no-binary pyzmq" in warned[0]
