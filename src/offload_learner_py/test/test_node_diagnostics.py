"""The nodes' /diagnostics updater reads ~diagnostic_period through rospy's parameter cache on every update, and
the cache holds only parameters that are set: NodeDiagnostics sets it (to its default when unset) so an idle node
does not call the master every second. No master here: the parameter server and the updater are fakes."""
import diagnostic_updater
import pytest
import rospy

from offload_learner_py.nodes import diagnostics


class FakeUpdater:
    def __init__(self):
        self.tasks = []

    def setHardwareID(self, hardware_id):
        self.hardware_id = hardware_id

    def add(self, name, fill):
        self.tasks.append(name)


@pytest.fixture
def params(monkeypatch):
    server, timers = {}, []
    monkeypatch.setattr(rospy, "get_param", lambda name, default=None: server.get(name, default))
    monkeypatch.setattr(rospy, "has_param", lambda name: name in server)
    monkeypatch.setattr(rospy, "set_param", server.__setitem__)
    monkeypatch.setattr(rospy, "Timer", lambda period, callback: timers.append(period.to_sec()))
    monkeypatch.setattr(diagnostic_updater, "Updater", FakeUpdater)
    return server, timers


def test_an_unset_period_is_set_to_the_default(params):
    server, timers = params
    diagnostics.NodeDiagnostics("cloud link", lambda: None)
    assert server == {"~diagnostic_period": diagnostics.UPDATER_PERIOD_S}
    assert timers == [diagnostics.UPDATER_PERIOD_S]


def test_a_period_set_by_the_user_is_kept(params):
    server, timers = params
    server["~diagnostic_period"] = 2.5
    diagnostics.NodeDiagnostics("offload decisions", lambda: None)
    assert server == {"~diagnostic_period": 2.5}
    assert timers == [2.5]
