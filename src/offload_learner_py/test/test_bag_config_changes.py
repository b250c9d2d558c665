"""A change made on the running learner (dynamic_reconfigure republishes its latched ~config) is read from a bag as a
setting of its own with the time it came into force, so an analysis splits the run's requests at it."""
from offload_learner_py.data import bags

from bagtools import make_requests, write


def test_each_distinct_setting_is_kept_with_the_time_it_was_first_recorded(tmp_path):
    from offload_demos.bag_writer import CONFIG_TOPIC, CONFIG_TYPE, config_definition, installed_definitions, \
        typestore_for

    store = typestore_for(*installed_definitions(), extra={CONFIG_TYPE: config_definition()})
    # requests 0-9 at probe rate 0.05, then a dynparam set to 1.0 before request 10, a refused change (no message),
    # back to 0.05 before request 30: that setting is kept once, from its first time
    probe_rate = {0: 0.05, 10: 1.0, 30: 0.05}
    stamps = {}

    def extra(bag, index, time_ns):
        if index in probe_rate:
            stamps[index] = time_ns
            bag.write(CONFIG_TOPIC, CONFIG_TYPE, {"mode": "deployed", "alpha": 0.5, "probe_rate": probe_rate[index]},
                      time_ns)
    data = bags.read_bags([write(tmp_path / "reconfigured.bag", make_requests(40), store=store, extra=extra)])
    configs = data.report.bags[0].configs
    assert [(config["probe_rate"], config["since_ns"]) for config in configs] == [(0.05, stamps[0]), (1.0, stamps[10])]
    assert stamps[0] < stamps[10] < stamps[30]
    assert data.report.recorded("probe_rate") == [0.05, 1.0]
