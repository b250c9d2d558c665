"""Algorithm 1 over a stream of steps: observe s_t, act epsilon-greedily, get r_t from both measured
latencies (eq. 10), store (s_t, a_t, r_t, s_t+1), train. Records what an evaluation needs: the
action taken and its propensity, the greedy action the policy would have taken at that moment (before
learning from the step), the loss and the reward."""
import sys
import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from offload_learner_py.data.dataset import TransitionTable
from offload_learner_py.core.dqn import DQNAgent, greedy_actions
from offload_learner_py.core.reward import CostWeights, reward


@dataclass
class OnlineRun:
    table: TransitionTable          # the steps with the actions the learner took
    greedy_action: np.ndarray       # argmax Q(s_t, .) just before acting at step t
    greedy_q: np.ndarray            # N x 2, Q(s_t, local) and Q(s_t, cloud) at that moment
    loss: np.ndarray                # loss of the gradient step after step t (nan when none ran)
    seconds: float                  # wall time of the whole run


def print_progress(step: int, steps: int, agent: DQNAgent, recent_loss: float, recent_reward: float) -> None:
    print(f"step {step}/{steps}  loss {recent_loss:.4f}  mean reward {recent_reward:+.3f}  "
          f"replay {len(agent.memory)}", file=sys.stderr, flush=True)


def run_online(agent: DQNAgent, stream: TransitionTable, weights: CostWeights = CostWeights(),
               progress: Optional[Callable] = None, progress_every: int = 100) -> OnlineRun:
    states = stream.states
    steps = len(stream)
    actions = np.zeros(steps, dtype=np.int64)
    propensities = np.zeros(steps)
    step_rewards = np.zeros(steps)
    greedy_q = np.zeros((steps, 2))
    losses = np.full(steps, np.nan)
    began = time.perf_counter()
    for t in range(steps):
        state = states[t]
        greedy_q[t] = agent.q_values(state)
        actions[t], propensities[t] = agent.act(state)
        step_rewards[t] = reward(int(actions[t]), float(stream.local_s[t]), float(stream.cloud_s[t]), weights)
        # The next request does not depend on this action; the last step has no successor yet, so
        # its own state stands in (its value only matters when gamma > 0).
        next_state = states[t + 1] if t + 1 < steps else state
        loss = agent.observe(state, int(actions[t]), step_rewards[t], next_state)
        if loss is not None:
            losses[t] = loss
        if progress is not None and ((t + 1) % progress_every == 0 or t + 1 == steps):
            window = slice(max(0, t + 1 - progress_every), t + 1)
            recent = losses[window]
            progress(t + 1, steps, agent, float(np.nanmean(recent)) if np.any(~np.isnan(recent)) else float("nan"),
                     float(step_rewards[window].mean()))
    greedy = greedy_actions(greedy_q)
    table = TransitionTable(t=stream.t, **stream.state_columns(), local_s=stream.local_s, cloud_s=stream.cloud_s,
                            action=actions, action_propensity=propensities, reward=step_rewards,
                            metadata={**stream.metadata, "logging_policy": "dqn_epsilon_greedy",
                                      "dqn_config": agent.config.to_dict()})
    return OnlineRun(table=table, greedy_action=greedy, greedy_q=greedy_q, loss=losses,
                     seconds=time.perf_counter() - began)
