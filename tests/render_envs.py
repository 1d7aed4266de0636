"""A Gymnasium task that renders without OpenGL, for tests of label_server.py:
`pebble.make_env("tests.render_envs:Frames-v0", render_mode="rgb_array")`."""

import gymnasium as gym
import numpy as np


class FramesEnv(gym.Env):
    """A dot that the actions push around a box, in 30-step episodes. render() draws it: a 120 x 160
    picture of the dot and a bar as long as the episode's step count, so every frame of an episode
    differs and a replay of the same seed and actions draws the same frames."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, render_mode=None):
        self.render_mode = render_mode
        self.observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.position = np.zeros(2)
        self.t = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.position = self.np_random.uniform(-0.5, 0.5, 2)
        self.t = 0
        return self.position.astype(np.float32), {}

    def step(self, action):
        self.position = np.clip(self.position + 0.15 * np.asarray(action), -1.0, 1.0)
        self.t += 1
        reward = -float(np.linalg.norm(self.position))
        return self.position.astype(np.float32), reward, False, False, {}

    def render(self):
        rows, columns = np.mgrid[0:120, 0:160]
        image = np.empty((120, 160, 3), np.uint8)
        image[:] = (228, 232, 222)
        x = 80 + 66 * self.position[0]
        y = 56 + 46 * self.position[1]
        image[(columns - x) ** 2 + (rows - y) ** 2 <= 11 ** 2] = (200, 40, 40)
        image[112:, :5 * self.t] = (60, 90, 170)
        return image


gym.register("Frames-v0", entry_point=FramesEnv, max_episode_steps=30)
