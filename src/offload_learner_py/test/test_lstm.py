import numpy as np
import pytest

from offload_learner_py.core.evaluation import accuracy
from offload_learner_py.core.lstm_baseline import LSTMConfig, LSTMPolicy


def test_defaults_are_the_paper_s():
    config = LSTMConfig()
    assert (config.hidden_size, config.batch_size, config.sequence_length, config.validation_fraction) == (4, 50, 8, 0.2)
    assert config.features == ("input_size",)


def test_predicts_both_times_from_input_size_and_picks_the_smaller(size_split_table):
    policy = LSTMPolicy(LSTMConfig(epochs=40, seed=1)).fit(size_split_table(500, 1))
    test = size_split_table(300, 2)
    predicted = policy.predict_latency_s(test)
    assert predicted.shape == (300, 2) and np.all(predicted > 0)
    assert np.array_equal(policy.choose(test), (predicted[:, 1] < predicted[:, 0]).astype(int))
    assert accuracy(policy.choose(test), test) > 0.85
    assert np.isfinite(policy.validation_loss)


def test_windows_hold_the_eight_latest_requests():
    policy = LSTMPolicy()
    windows = policy._windows(np.arange(10, dtype=float)[:, None])
    assert windows.shape == (10, 8, 1)
    assert windows[9, :, 0].tolist() == [2, 3, 4, 5, 6, 7, 8, 9]
    assert windows[0, :, 0].tolist() == [0] * 8  # no history yet: the first request repeats


def test_same_seed_same_model(size_split_table):
    train, test = size_split_table(200, 1), size_split_table(50, 2)
    a = LSTMPolicy(LSTMConfig(epochs=3, seed=5)).fit(train).predict_latency_s(test)
    b = LSTMPolicy(LSTMConfig(epochs=3, seed=5)).fit(train).predict_latency_s(test)
    assert np.array_equal(a, b)


def test_unknown_features_are_rejected():
    with pytest.raises(ValueError):
        LSTMPolicy(LSTMConfig(features=("gpu",)))


def test_the_lstm_fit_shows_its_epochs_when_asked(capsys):
    import numpy as np

    from offload_learner_py.core.lstm_baseline import LSTMConfig, LSTMPolicy
    from offload_learner_py.data.dataset import TransitionTable
    d = np.random.default_rng(0).uniform(0.1, 2, 60)
    table = TransitionTable(t=np.arange(60), input_size=d, cpu_availability=np.full(60, 0.5),
                            round_trip_s=np.full(60, 0.05), local_s=0.1 * d, cloud_s=np.full(60, 0.1),
                            action=np.zeros(60, np.int64), action_propensity=np.ones(60), reward=np.zeros(60))
    LSTMPolicy(LSTMConfig(epochs=3), progress=True).fit(table)
    assert "LSTM baseline (lstm)" in capsys.readouterr().err
    LSTMPolicy(LSTMConfig(epochs=3)).fit(table)
    assert "LSTM baseline" not in capsys.readouterr().err
