"""The paper's comparison model (section V.C): an LSTM that predicts both execution times, l_local
and l_cloud, from the input size, and picks the smaller. Hidden size 4, batch 50, 8 steps per
batch (each sample is a window of the 8 latest requests, the prediction is for the last one), and
an 80:20 chronological training:validation split; the epoch with the best validation loss is kept."""
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.data.dataset import TransitionTable
from offload_learner_py.core.policies import Policy
from offload_learner_py.core.state import STATE_FIELDS, STATE_SCHEMA

FEATURE_COLUMNS = STATE_FIELDS


@dataclass(frozen=True)
class LSTMConfig:
    hidden_size: int = 4
    """LSTM hidden units (paper: 4)."""
    batch_size: int = 50
    """windows per gradient step (paper: 50)."""
    sequence_length: int = 8
    """requests per window (paper: 8 steps per batch)."""
    validation_fraction: float = 0.2
    """last share of the training windows held out to pick the epoch (paper: 80:20)."""
    epochs: int = 60
    """passes over the training windows."""
    learning_rate: float = 1e-2
    """Adam step size."""
    features: tuple = ("input_size",)
    """state columns fed to the LSTM (paper: input size only)."""
    seed: int = 1
    """seed of the weights and the batch order."""


class LatencyLSTM(nn.Module):
    def __init__(self, n_features: int, hidden_size: int):
        super().__init__()
        self.lstm = nn.LSTM(n_features, hidden_size, batch_first=True)
        self.head = nn.Linear(hidden_size, 2)  # log l_local, log l_cloud, standardised

    def forward(self, x):
        out, _ = self.lstm(x)
        return self.head(out[:, -1])


class LSTMPolicy(Policy):
    name = "lstm"

    def __init__(self, config: LSTMConfig = LSTMConfig(), progress: bool = False):
        unknown = set(config.features) - set(FEATURE_COLUMNS)
        if unknown or not config.features:
            raise ValueError(f"features must be a non-empty subset of {FEATURE_COLUMNS}, got {config.features}")
        self.config = config
        self.progress = progress   # a progress bar over the epochs on stderr
        self.model = None
        self.validation_loss = float("nan")

    def _features(self, table: TransitionTable) -> np.ndarray:
        columns = []
        for name in self.config.features:   # on the schema's log scale where it hints one (the input size)
            values, floor = getattr(table, name), STATE_SCHEMA[name].log_floor
            columns.append(values if floor is None else np.log(np.maximum(values, 0.0) + floor))
        return np.stack(columns, axis=1)

    def _windows(self, features: np.ndarray) -> np.ndarray:
        """Window ending at each row; the first rows repeat the first request for lack of history."""
        pad = np.repeat(features[:1], self.config.sequence_length - 1, axis=0)
        padded = np.concatenate([pad, features])
        index = np.arange(len(features))[:, None] + np.arange(self.config.sequence_length)[None, :]
        return padded[index]

    def fit(self, train):
        config = self.config
        features = self._features(train)
        self._feature_mean, self._feature_scale = features.mean(0), np.maximum(features.std(0), 1e-6)
        targets = np.log(np.stack([train.local_s, train.cloud_s], axis=1))
        self._target_mean, self._target_scale = targets.mean(0), np.maximum(targets.std(0), 1e-6)
        x = torch.tensor(self._windows((features - self._feature_mean) / self._feature_scale), dtype=torch.float32)
        y = torch.tensor((targets - self._target_mean) / self._target_scale, dtype=torch.float32)
        split = max(1, int(round(len(x) * (1.0 - config.validation_fraction))))
        x_train, y_train, x_valid, y_valid = x[:split], y[:split], x[split:], y[split:]
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(config.seed)
            model = LatencyLSTM(len(config.features), config.hidden_size)
        optimizer = torch.optim.Adam(model.parameters(), lr=config.learning_rate)
        rng = np.random.default_rng(config.seed)
        best_loss, best_state = float("inf"), None
        epochs = range(config.epochs)
        if self.progress:
            import sys

            from tqdm import tqdm
            epochs = tqdm(epochs, desc=f"LSTM baseline ({self.name})", unit="epoch", file=sys.stderr)
        for _ in epochs:
            order = rng.permutation(len(x_train))
            for start in range(0, len(order), config.batch_size):
                batch = torch.from_numpy(order[start:start + config.batch_size])
                loss = nn.functional.mse_loss(model(x_train[batch]), y_train[batch])
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
            with torch.no_grad():
                held_out = (x_valid, y_valid) if len(x_valid) else (x_train, y_train)
                valid_loss = float(nn.functional.mse_loss(model(held_out[0]), held_out[1]))
            if valid_loss < best_loss:
                best_loss, best_state = valid_loss, {k: v.clone() for k, v in model.state_dict().items()}
        model.load_state_dict(best_state)
        self.model, self.validation_loss = model, best_loss
        return self

    def predict_latency_s(self, table: TransitionTable) -> np.ndarray:
        """N x 2 predicted (l_local, l_cloud) in seconds."""
        if self.model is None:
            raise RuntimeError("fit the LSTM policy first")
        x = self._windows((self._features(table) - self._feature_mean) / self._feature_scale)
        with torch.no_grad():
            predicted = self.model(torch.tensor(x, dtype=torch.float32)).numpy()
        return np.exp(predicted * self._target_scale + self._target_mean)

    def choose(self, table):
        predicted = self.predict_latency_s(table)
        return np.where(predicted[:, CLOUD] < predicted[:, LOCAL], CLOUD, LOCAL).astype(np.int64)
