"""Learner records for the tests: a decision and an outcome with the fields the messages carry."""
from types import SimpleNamespace

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.reward import reward
from statetools import PLAN_RATE


def decision(request_id, action=LOCAL, d=1.0, u=0.5, b=0.05, propensity=0.95, p=PLAN_RATE):
    return SimpleNamespace(request_id=request_id, input_size=d, cpu_availability=u, round_trip_s=b,
                           local_plan_rate=p, action=action,
                           action_propensity=propensity, q_local=0.0, q_cloud=0.1, policy="dqn", model_steps=3,
                           probe=True)


def outcome(request_id, action=LOCAL, local_s=0.2, cloud_s=0.1, reward_valid=True, timeout=False, delivered=None):
    return SimpleNamespace(request_id=request_id, action=action,
                           delivered=CLOUD if delivered is None and cloud_s < local_s else (delivered or LOCAL),
                           local_measured=True, local_s=local_s, local_status=0, cloud_measured=True, cloud_s=cloud_s,
                           cloud_status=9 if timeout else 0, cloud_timeout=timeout, reward_valid=reward_valid,
                           reward=reward(action, local_s, cloud_s) if reward_valid else float("nan"),
                           loss_valid=False, loss=float("nan"), delivered_s=min(local_s, cloud_s))
