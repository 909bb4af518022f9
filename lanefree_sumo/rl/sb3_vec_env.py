"""LaneFree-v0's vector entry point as a Stable-Baselines3 ``VecEnv``: K rings in one process for SB3's algorithms.

SB3 steps a ``VecEnv`` of its own kind, not a gymnasium ``VectorEnv``; its one-liner
``make_vec_env("LaneFree-v0", n_envs=K)`` builds a ``DummyVecEnv`` of K LaneFree-v0 environments stepped one after
another. :class:`BatchedVecEnv` is the same K environments as one :class:`~lanefree_sumo.rl.vector_env.
LaneFreeVectorEnv` (one array program over the K worlds) in SB3's conventions::

    from stable_baselines3 import SAC
    from stable_baselines3.common.vec_env import VecMonitor
    from lanefree_sumo.rl.sb3_vec_env import BatchedVecEnv

    model = SAC("MlpPolicy", VecMonitor(BatchedVecEnv(8)), learning_starts=100)

Sub-environment k equals environment k of ``DummyVecEnv`` over LaneFree-v0 with the same config, bit for bit
(``tests/rl/test_sb3_vec_env.py``): ``seed(s)`` seeds it with ``s + k`` at the next reset (no seed: fresh entropy);
an episode's end resets it in the same step (SB3's autoreset), its last observation in
``info["terminal_observation"]`` and ``info["TimeLimit.truncated"]`` set when the step limit, not a collision,
ended it; rewards are float32 as ``DummyVecEnv`` stores them. ``infos[k]`` holds LaneFree-v0's step ``info``
(the reward terms, the collision events, ``episode_metrics`` at an episode's end); ``reset_infos[k]`` its reset
``info`` (``episode_seed``). What runs batched is what the vector entry point runs (one learning vehicle on the
ring, numpy backend, no shield); anything else is refused in one line.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvObs, VecEnvStepReturn

from lanefree_sumo.config import LaneFreeConfig
from lanefree_sumo.rl.vector_env import LaneFreeVectorEnv


def env_infos(info: Mapping[str, Any], n: int) -> list[dict[str, Any]]:
    """Gymnasium's vector ``info`` (every key an array over the sub-environments, its ``_key`` mask beside it; a
    dict value nested the same way) as one dict per sub-environment holding the keys its mask marks."""
    out: list[dict[str, Any]] = [{} for _ in range(n)]
    for key, value in info.items():
        if key.startswith("_"):
            continue
        mask = info.get(f"_{key}", np.ones(n, dtype=bool))
        nested = env_infos(value, n) if isinstance(value, Mapping) else None
        for k in np.flatnonzero(mask):
            out[k][key] = nested[k] if nested is not None else value[k]
    return out


class BatchedVecEnv(VecEnv):
    """K LaneFree-v0 environments as one batched world, behind SB3's ``VecEnv`` (module docstring).

    :param n_envs: K ≥ 1.
    :param config: LaneFree-v0's config (a dict of overrides or a :class:`~lanefree_sumo.config.LaneFreeConfig`),
        the same for every sub-environment.
    :param render_mode: ``"rgb_array"`` (``get_images()``: one frame per sub-environment; SB3's ``render()`` tiles
        them) or None."""

    def __init__(self, n_envs: int = 1, config: LaneFreeConfig | Mapping[str, Any] | None = None,
                 render_mode: str | None = None) -> None:
        self.venv = LaneFreeVectorEnv(n_envs, config, render_mode=render_mode)
        self.render_mode = render_mode
        super().__init__(self.venv.num_envs, self.venv.single_observation_space, self.venv.single_action_space)
        self._actions: np.ndarray | None = None

    def _obs(self, obs: Any) -> VecEnvObs:
        """The observations in the observation space's dtype, as ``DummyVecEnv`` buffers them."""
        if isinstance(obs, Mapping):
            assert isinstance(self.observation_space, spaces.Dict)
            return {name: np.asarray(v, dtype=self.observation_space[name].dtype) for name, v in obs.items()}
        return np.asarray(obs, dtype=self.observation_space.dtype)

    def reset(self) -> VecEnvObs:
        """Start an episode in every sub-environment, with the seeds :meth:`seed` set (once)."""
        seeds = None if all(s is None for s in self._seeds) else list(self._seeds)
        obs, info = self.venv.reset(seed=seeds)
        self.reset_infos = env_infos(info, self.num_envs)
        self._reset_seeds()
        self._reset_options()
        return self._obs(obs)

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self) -> VecEnvStepReturn:
        """One step of every sub-environment; an ended episode's sub-environment starts its next one at once."""
        if self._actions is None:
            raise RuntimeError("step_wait() without step_async(actions)")
        actions, self._actions = self._actions, None
        obs, reward, terminated, truncated, info = self.venv.step(actions)
        obs = self._obs(obs)
        done = terminated | truncated
        infos = env_infos(info, self.num_envs)
        for k in range(self.num_envs):
            infos[k]["TimeLimit.truncated"] = bool(truncated[k] and not terminated[k])
        if done.any():
            for ended in np.flatnonzero(done):
                infos[ended]["terminal_observation"] = (
                    {name: v[ended] for name, v in obs.items()} if isinstance(obs, dict) else obs[ended])
            # the vector env's reset of the ended ones: their next episodes at once (SB3's autoreset)
            fresh, reset_info = self.venv.reset(options={"reset_mask": done})
            for k, got in enumerate(env_infos(reset_info, self.num_envs)):
                if done[k]:
                    self.reset_infos[k] = got
            obs = self._obs(fresh)
        return obs, reward.astype(np.float32), done, infos

    def close(self) -> None:
        self.venv.close()

    def get_images(self) -> Sequence[np.ndarray | None]:
        """One ``H × W × 3`` frame per sub-environment (``render_mode="rgb_array"``), else Nones."""
        frames = self.venv.render()
        return list(frames) if frames is not None else [None] * self.num_envs

    # -- SB3's per-environment access: the sub-environments are rows of one world ------------------------------
    def _indices(self, indices: VecEnvIndices) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        return [int(indices)] if isinstance(indices, int | np.integer) else [int(i) for i in indices]

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """The attribute ``attr_name`` of LaneFree-v0 that every sub-environment shares (``render_mode``, the
        spaces, ``cfg``); AttributeError for any other."""
        shared = {"render_mode": self.render_mode, "cfg": self.venv.cfg,
                  "observation_space": self.observation_space, "action_space": self.action_space}
        if attr_name not in shared:
            raise AttributeError(f"BatchedVecEnv's sub-environments share {', '.join(shared)}; {attr_name!r} is "
                                 "none of them")
        return [shared[attr_name] for _ in self._indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        raise AttributeError(f"BatchedVecEnv's sub-environments are rows of one world: {attr_name!r} cannot be set "
                             "on some of them; build a new BatchedVecEnv with another config")

    def env_method(self, method_name: str, *method_args: Any, indices: VecEnvIndices = None,
                   **method_kwargs: Any) -> list[Any]:
        raise AttributeError(f"BatchedVecEnv's sub-environments are rows of one world, not objects with methods "
                             f"({method_name!r}); use make_vec_env('LaneFree-v0', n_envs) for per-env methods")

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        """No sub-environment is wrapped (SB3's Monitor goes around the whole: ``VecMonitor``)."""
        return [False for _ in self._indices(indices)]
