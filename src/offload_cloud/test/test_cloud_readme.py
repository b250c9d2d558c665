"""the offload_cloud README's worked example (load a map, connect with CURVE keys, plan, read the path) runs as
written against a local server; only the host name is pointed at it."""
import os
import re
import subprocess
import sys
from pathlib import Path

from cloud_test_helpers import make_keys, start_server

PACKAGE = Path(__file__).resolve().parents[1]
WORKSPACE = PACKAGE.parents[1]
PLACEHOLDER = "tcp://cloud-host:5555"


def example_code() -> str:
    text = (PACKAGE / "README.md").read_text()
    section = text.split("## Planning through the client (Python)\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, re.S)
    assert len(blocks) == 1, "the section holds one python example"
    assert PLACEHOLDER in blocks[0] and "~/keys/robot1" in blocks[0]
    return blocks[0]


def test_readme_example_plans_through_the_client(tmp_path):
    home = tmp_path / "home"
    server_keys = make_keys(home / "keys", clients=("robot1",))   # the layout the Keys section writes
    server = start_server(server_keys, workers=1)
    try:
        code = example_code().replace(PLACEHOLDER, server.endpoint)
        env = {**os.environ, "HOME": str(home)}
        done = subprocess.run([sys.executable, "-c", code], cwd=WORKSPACE, env=env, capture_output=True,
                              text=True, timeout=120)
    finally:
        server.stop()
    assert done.returncode == 0, done.stderr
    # The comment's cells are the ones the example computes, and the path ends on the goal (x, y).
    assert "(159, 189) and (237, 209)" in code
    assert re.fullmatch(r"\d+ cells, \d+\.\d\d m, ends at cell \(237, 209\); planned in [\d.]+ ms of a [\d.]+ ms "
                        r"round trip\n", done.stdout), done.stdout
