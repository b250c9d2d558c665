"""The robot guard's bookkeeping (online/model_guard.ModelGuard): which versions it watches, when it judges, the means
its verdict reports and the log line an operator reads (found by `make mutate` over model_guard.py, #31: the
verdict's means and text, the baseline's minimum size, the version check and `watching` survived)."""
from offload_learner_py.online.model_guard import GuardConfig, ModelGuard

A, B, C = "a" * 64, "b" * 64, "c" * 64


def fed(guard, version, latencies):
    return [guard.observe(version, x) for x in latencies]


def test_the_verdict_reports_both_means_and_says_them_in_its_line():
    guard = ModelGuard(GuardConfig(requests=4))
    fed(guard, A, [0.010, 0.020, 0.030, 0.040])
    guard.begin(B, A)
    assert guard.watching == B
    verdicts = fed(guard, B, [0.100, 0.110, 0.120, 0.130])
    assert verdicts[:3] == [None, None, None]
    verdict = verdicts[3]
    assert verdict.worse and guard.watching is None
    assert (verdict.mean_new_s, verdict.mean_old_s, verdict.n_new, verdict.n_old) == \
        (0.115, 0.025, 4, 4)
    line = verdict.describe()
    assert line.startswith(f"model {B[:12]} is worse than {A[:12]}: mean 115.0 ms over its first 4 requests "
                           f"against 25.0 ms over the last 4")
    assert B[:13] not in line


def test_a_version_without_a_predecessor_is_named_as_the_model_before():
    guard = ModelGuard(GuardConfig(requests=2))
    fed(guard, "", [0.02, 0.03])
    guard.begin(B, "")
    verdict = fed(guard, B, [0.02, 0.03])[-1]
    assert not verdict.worse
    assert f"{B[:12]} is not worse than the model before: mean 25.0 ms" in verdict.describe()


def test_a_baseline_of_half_the_window_is_enough_and_less_is_not():
    guard = ModelGuard(GuardConfig(requests=10))
    fed(guard, A, [0.01] * 4)
    guard.begin(B, A)
    assert guard.watching is None            # 4 of 10: too few to judge against
    fed(guard, B, [0.01] * 5)
    guard.begin(C, B)
    assert guard.watching == C               # 5 of 10: n // 2
    guard = ModelGuard(GuardConfig(requests=3))
    fed(guard, A, [0.01, 0.02])
    guard.begin(B, A)
    assert guard.watching == B               # at least 2 whatever the window


def test_only_the_watched_version_is_judged_and_once():
    guard = ModelGuard(GuardConfig(requests=3))
    fed(guard, B, [0.01, 0.02, 0.03])
    guard.begin(C, B)
    # rows of another version that arrive late (decided before the swap) never complete the watched one's window:
    # a version sorting below the watched one as well as above it
    assert fed(guard, A, [0.5] * 5) == [None] * 5
    assert fed(guard, "d" * 64, [0.5] * 5) == [None] * 5
    assert guard.watching == C
    verdicts = fed(guard, C, [0.01, 0.02, 0.03, 0.5, 0.5])
    assert [v is not None for v in verdicts] == [False, False, True, False, False]
