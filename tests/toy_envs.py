"""Tiny Gymnasium tasks for tests, made by `pebble.py --env-id tests.toy_envs:<id>`."""

import gymnasium as gym
import numpy as np


class ConstantPenaltyEnv(gym.Env):
    """Reward -1 at every step of 40-step episodes: every segment of H steps returns exactly -H, so a
    Skip teacher with eps_skip = 0.5 (delta_skip = -H / 2) skips every query."""

    def __init__(self):
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.state = np.zeros(3, dtype=np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.state = self.np_random.normal(size=3).astype(np.float32)
        return self.state, {}

    def step(self, action):
        self.state = (self.state + 0.1 * np.append(action, 0.0)).astype(np.float32)
        return self.state, -1.0, False, False, {}


gym.register("ConstantPenalty-v0", entry_point=ConstantPenaltyEnv, max_episode_steps=40)


class HugeRewardEnv(ConstantPenaltyEnv):
    """Reward 1e30 at every step: finite, but a squared TD or value error overflows float32 to inf."""

    def step(self, action):
        return super().step(action)[0], 1e30, False, False, {}


class NaNRewardEnv(ConstantPenaltyEnv):
    """Returns a NaN reward on the 300th step of its life (a broken simulator)."""

    steps = 0

    def step(self, action):
        self.steps += 1
        return super().step(action)[0], float("nan") if self.steps == 300 else -1.0, False, False, {}


gym.register("HugeReward-v0", entry_point=HugeRewardEnv, max_episode_steps=40)
gym.register("NaNReward-v0", entry_point=NaNRewardEnv, max_episode_steps=40)


class NaNSeededEpisodeEnv(ConstantPenaltyEnv):
    """Returns a NaN reward at the 20th step of an episode whose reset drew a third coordinate above 1: a simulator
    that breaks in some episodes, which the episode's seed decides (so a resumed run meets it at the same step)."""

    def reset(self, *, seed=None, options=None):
        self.t = 0
        return super().reset(seed=seed, options=options)

    def step(self, action):
        self.t += 1
        broken = self.t == 20 and self.state[2] > 1.0
        return super().step(action)[0], float("nan") if broken else -1.0, False, False, {}


gym.register("NaNSeededEpisode-v0", entry_point=NaNSeededEpisodeEnv, max_episode_steps=40)
