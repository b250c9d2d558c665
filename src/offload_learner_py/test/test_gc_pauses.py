"""The processes on a request's path freeze their start-up heap before they serve (gc_pauses.py): a full
collection over rospy's, torch's and numpy's objects cost 130 ms of CPU and showed as 900 ms cloud calls."""
import subprocess
import sys

import pytest

from offload_cloud import server_cli
from offload_learner_py.nodes import cloud_bridge


def test_frozen_objects_are_out_of_the_collectors_reach():
    # A fresh interpreter, so the count is this heap's: 200,000 long-lived objects made at "start-up".
    script = (
        "import gc\n"
        "from offload_cloud.gc_pauses import freeze_startup_heap\n"
        "keep = [[k] for k in range(200000)]\n"
        "tracked = len(gc.get_objects())\n"
        "frozen = freeze_startup_heap()\n"
        "print(tracked, frozen, len(gc.get_objects()))\n")
    tracked, frozen, left = map(int, subprocess.run([sys.executable, "-c", script], check=True, capture_output=True,
                                                    text=True).stdout.split())
    assert tracked > 200000
    assert frozen >= 200000
    assert left < 0.01 * tracked, "a full collection would still walk the start-up heap"


class Calls(list):
    def record(self, name, result=None):
        def call(*args, **kwargs):
            self.append(name)
            return result
        return call


def test_the_cloud_bridge_freezes_its_heap_before_it_serves(monkeypatch):
    calls = Calls()
    monkeypatch.setattr(cloud_bridge.rospy, "init_node", calls.record("init"))
    monkeypatch.setattr(cloud_bridge, "read_parameters", calls.record("parameters"))
    monkeypatch.setattr(cloud_bridge.rospy, "get_param", lambda name, default=None: default)
    monkeypatch.setattr(cloud_bridge, "CloudBridgeNode", calls.record("node"))
    monkeypatch.setattr(cloud_bridge, "freeze_startup_heap", calls.record("freeze"))
    monkeypatch.setattr(cloud_bridge.rospy, "spin", calls.record("spin"))
    cloud_bridge.main()
    assert calls == ["init", "parameters", "node", "freeze", "spin"]


class FakeServer:
    endpoint = "tcp://127.0.0.1:1"
    metrics = None   # no --metrics-bind

    def __init__(self, calls):
        self.calls = calls

    def run(self):
        self.calls.append("run")


def test_the_cloud_server_freezes_its_heap_before_it_serves(monkeypatch):
    calls = Calls()
    monkeypatch.setattr(server_cli, "CloudServer", lambda config: calls.append("server") or FakeServer(calls))
    monkeypatch.setattr(server_cli, "freeze_startup_heap", calls.record("freeze"))
    monkeypatch.setattr(server_cli.signal, "signal", lambda *args: None)
    assert server_cli.main(["--insecure", "--bind", "tcp://127.0.0.1:0"]) == 0
    assert calls == ["server", "freeze", "run"]


@pytest.mark.parametrize("module", [cloud_bridge, server_cli])
def test_it_is_the_one_helper(module):
    from offload_cloud import gc_pauses
    assert module.freeze_startup_heap is gc_pauses.freeze_startup_heap
