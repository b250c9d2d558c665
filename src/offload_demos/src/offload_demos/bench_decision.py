"""Benchmark of one offloading decision (raw state in, action and both Q-values out), as the robot
makes it per planning request. Prints p50/p99 in microseconds for torch eager, TorchScript, a numpy forward pass
(the robot's path until the decision was compiled) and the compiled fast path the robot uses (FastDecision), all
measured in this run on the same states.

Then the numpy and the compiled paths at a robot's pace: one decision every --paced-gap-ms with the caches flushed
before each, while a process keeps every other core busy (the planner, the robot's other work), against the same
path back to back (above) in the same run. Prints wall time and the process's CPU time (every thread) per decision.

    python -m offload_demos.bench_decision [--decisions 20000] [--budget-us 100] [--paced-decisions 100]
"""
import argparse
import math
import os
import resource
import subprocess
import sys
import time
import warnings
from typing import Callable, Dict

import numpy as np
import torch

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.normalisation import StateNormalisation
from offload_learner_py.core.state import STATE_SCHEMA, STATE_SIZE


def measure_us(decide: Callable[..., tuple], states: np.ndarray, warm_up: int = 500) -> Dict[str, float]:
    """Wall time of each decide(*state) call (the state's fields in schema order) in microseconds: p50, p99, max."""
    rows = [tuple(float(v) for v in row) for row in states]
    for row in rows[:warm_up]:
        decide(*row)
    samples = np.empty(len(rows))
    clock = time.perf_counter_ns
    for i, row in enumerate(rows):
        began = clock()
        decide(*row)
        samples[i] = clock() - began
    samples /= 1e3
    return {"p50_us": float(np.percentile(samples, 50)), "p99_us": float(np.percentile(samples, 99)),
            "max_us": float(samples.max())}


def paced_us(decide: Callable[..., tuple], states: np.ndarray, gap_s: float, flush: np.ndarray) -> Dict[str, float]:
    """Each decide(*state) after a pause of gap_s and a pass over `flush` (larger than the caches), as a request meets
    it on a robot: wall time p50/p99 and the process's CPU time (all threads, spinning BLAS workers included) per
    decision, in microseconds."""
    samples = np.empty(len(states))
    clock = time.perf_counter_ns
    cpu = 0.0
    for i, row in enumerate(tuple(float(v) for v in r) for r in states):
        time.sleep(gap_s)
        flush[::64] += 1
        before = resource.getrusage(resource.RUSAGE_SELF)
        began = clock()
        decide(*row)
        samples[i] = clock() - began
        after = resource.getrusage(resource.RUSAGE_SELF)
        cpu += (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    samples /= 1e3
    return {"p50_us": float(np.percentile(samples, 50)), "p99_us": float(np.percentile(samples, 99)),
            "cpu_us": 1e6 * cpu / len(states)}


def busy_other_cores():
    """A process that keeps every core but this one busy for as long as it lives (the robot's planner); this thread
    is held to the first core meanwhile (paced() gives it its cores back)."""
    cores = sorted(os.sched_getaffinity(0))
    if len(cores) < 2:
        return []
    mine = cores[0]
    os.sched_setaffinity(0, {mine})
    return [subprocess.Popen([sys.executable, "-c", f"import os; os.sched_setaffinity(0, {{{core}}})\nwhile True: pass"])
            for core in cores[1:]]


def example_states(count: int, seed: int) -> np.ndarray:
    """States spread like the synthetic streams: d over four decades, u 0.5-0.7, b about 30 ms, and p over the local
    planning rates measured here (4e6-7e7 cells/s)."""
    rng = np.random.default_rng(seed)
    columns = {"input_size": 10.0 ** rng.uniform(-4.5, -0.5, count), "cpu_availability": rng.uniform(0.5, 0.7, count),
               "round_trip_s": rng.uniform(0.0285, 0.0315, count), "local_plan_rate": 10.0 ** rng.uniform(2.0, 3.0, count)}
    return STATE_SCHEMA.stack(columns.__getitem__)


def decision_paths(agent: DQNAgent) -> Dict[str, Callable]:
    def eager(*state):
        q = agent.q_values(np.array(state))
        return (CLOUD if q[CLOUD] > q[LOCAL] else LOCAL), float(q[LOCAL]), float(q[CLOUD])

    paths = {"torch eager": eager}
    try:
        with warnings.catch_warnings():
            # Deprecated in torch 2.x but still the usual way to ship a network to C++/robots: it is
            # measured here so the choice of the numpy path rests on numbers.
            warnings.simplefilter("ignore", DeprecationWarning)
            scripted = torch.jit.script(agent.q_network.eval())
        normalisation = agent.normalisation

        def torchscript(*state):
            with torch.no_grad():
                q = scripted(torch.from_numpy(normalisation.apply(np.array(state)))).numpy()
            return (CLOUD if q[CLOUD] > q[LOCAL] else LOCAL), float(q[LOCAL]), float(q[CLOUD])

        paths["torchscript"] = torchscript
    except Exception as error:  # TorchScript is optional: report why it is missing and go on
        print(f"torchscript unavailable: {error}", file=sys.stderr)
    paths["numpy"] = numpy_decision(agent)
    paths["fast path"] = agent.fast_decision().decide
    return paths


def numpy_decision(agent: DQNAgent) -> Callable:
    """The baseline: the robot's decision before it was compiled (FastDecision up to 7cc2737), as numpy calls. The
    state is normalised in Python floats, then two calls a hidden layer, its bias a row fed by a unit held at 1."""
    fast = agent.fast_decision()
    layers = []
    for i, (w, b) in enumerate(zip(fast.weights, fast.biases)):
        hidden = i < len(fast.weights) - 1
        layer = np.zeros((w.shape[0] + 1, w.shape[1] + hidden), dtype=np.float32)
        layer[:-1, :w.shape[1]], layer[-1, :w.shape[1]] = w, b
        if hidden:
            layer[-1, -1] = 1.0
        layers.append(layer)
    normalisation = agent.normalisation
    mean = [float(m) for m in normalisation.mean]
    inverse_scale = [1.0 / float(s) for s in normalisation.scale]
    logs = STATE_SCHEMA.log_columns if normalisation.log_input_size else ()

    def decide(*state):
        if logs:
            state = list(state)
            for i, floor in logs:
                state[i] = math.log(max(state[i], 0.0) + floor)
        x = [(value - m) * inverse for value, m, inverse in zip(state, mean, inverse_scale)]
        x.append(1.0)
        h = np.array(x, dtype=np.float32)
        for layer in layers[:-1]:
            h = h @ layer
            np.maximum(h, 0.0, out=h)
        q_local, q_cloud = (h @ layers[-1]).tolist()
        return (CLOUD if q_cloud > q_local else LOCAL), q_local, q_cloud

    return decide


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--decisions", type=int, default=20000)
    parser.add_argument("--budget-us", type=float, default=100.0, help="p99 budget of the fast path")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1: one decision is tiny)")
    parser.add_argument("--paced-decisions", type=int, default=100, help="decisions at a robot's pace (0: none)")
    parser.add_argument("--paced-gap-ms", type=float, default=150.0, help="pause before each paced decision")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    states = example_states(args.decisions, args.seed)
    agent = DQNAgent(DQNConfig(seed=args.seed), StateNormalisation.fit(states))
    paths = decision_paths(agent)
    check = states[:200]
    eager_actions = [paths["torch eager"](*row)[0] for row in check]
    for name in ("numpy", "fast path"):
        if [paths[name](*row)[0] for row in check] != eager_actions:
            print(f"{name} disagrees with torch eager", file=sys.stderr)
            return 1
    print(f"one decision (state in, action and both Q-values out), {args.decisions} decisions, "
          f"network {STATE_SIZE} -> {' -> '.join(map(str, agent.config.hidden_sizes))} -> 2, "
          f"torch threads {args.threads}")
    results = {}
    for name, decide in paths.items():
        results[name] = measure_us(decide, states)
        r = results[name]
        print(f"  {name:16s} p50 {r['p50_us']:7.1f} us   p99 {r['p99_us']:7.1f} us   max {r['max_us']:8.1f} us")
    fast_p99 = results["fast path"]["p99_us"]
    verdict = "within" if fast_p99 <= args.budget_us else "OVER"
    print(f"fast path p99 {fast_p99:.1f} us: {verdict} the {args.budget_us:.0f} us budget")
    if args.paced_decisions:
        for name in ("numpy", "fast path"):
            paced(name, paths[name], states[:args.paced_decisions], args.paced_gap_ms / 1e3, results[name])
    return 0 if fast_p99 <= args.budget_us else 2


def paced(name: str, decide: Callable, states: np.ndarray, gap_s: float, back_to_back: Dict[str, float]) -> None:
    flush = np.zeros(64 << 20, dtype=np.uint8)
    cores = os.sched_getaffinity(0)
    burners = busy_other_cores()
    try:
        r = paced_us(decide, states, gap_s, flush)
    finally:
        for burner in burners:
            burner.kill()
            burner.wait()
        os.sched_setaffinity(0, cores)
    print(f"{name} at a robot's pace: {len(states)} decisions {1e3 * gap_s:.0f} ms apart, caches flushed, "
          f"{len(burners)} other core(s) busy: p50 {r['p50_us']:.1f} us, p99 {r['p99_us']:.1f} us, CPU "
          f"{r['cpu_us']:.1f} us a decision (all threads); {r['p50_us'] / back_to_back['p50_us']:.1f}x the p50 back "
          f"to back")


if __name__ == "__main__":
    sys.exit(main())
