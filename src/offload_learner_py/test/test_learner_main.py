"""The learner node freezes its start-up heap (rospy, torch) before it serves requests: a full collection
over it cost 130 ms of CPU, 4-5 times that in a busy robot's CPU budget (offload_cloud.gc_pauses)."""
from offload_learner_py.nodes import learner


def test_the_learner_freezes_its_heap_after_start_up_and_before_it_serves(monkeypatch):
    calls = []
    monkeypatch.setattr(learner.rospy, "init_node", lambda *a, **k: calls.append("init"))
    monkeypatch.setattr(learner, "LearnerNode", lambda: calls.append("node"))
    monkeypatch.setattr(learner, "freeze_startup_heap", lambda: calls.append("freeze"))
    monkeypatch.setattr(learner.rospy, "spin", lambda: calls.append("spin"))
    learner.main()
    assert calls == ["init", "node", "freeze", "spin"]
