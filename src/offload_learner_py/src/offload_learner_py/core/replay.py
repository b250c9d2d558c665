"""FIFO replay memory of Algorithm 1: a preallocated numpy ring, oldest experience replaced first. A row holds
one raw state, STATE_SIZE wide (the state schema's fields in order)."""
import numpy as np

from offload_learner_py.core.state import STATE_SIZE


class ReplayMemory:
    def __init__(self, capacity: int, state_size: int = STATE_SIZE):
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.capacity = capacity
        self.states = np.zeros((capacity, state_size), dtype=np.float32)
        self.actions = np.zeros(capacity, dtype=np.int64)
        self.rewards = np.zeros(capacity, dtype=np.float32)
        self.next_states = np.zeros((capacity, state_size), dtype=np.float32)
        self._next_slot = 0
        self._size = 0

    def __len__(self) -> int:
        return self._size

    def add(self, state, action: int, reward: float, next_state) -> None:
        slot = self._next_slot
        self.states[slot] = state
        self.actions[slot] = action
        self.rewards[slot] = reward
        self.next_states[slot] = next_state
        self._next_slot = (slot + 1) % self.capacity
        self._size = min(self._size + 1, self.capacity)

    def sample(self, batch_size: int, rng: np.random.Generator):
        """Uniform minibatch (with replacement, as the ring may hold fewer than batch_size)."""
        if self._size == 0:
            raise ValueError("cannot sample from an empty replay memory")
        index = rng.integers(0, self._size, size=batch_size)
        return self.states[index], self.actions[index], self.rewards[index], self.next_states[index]
