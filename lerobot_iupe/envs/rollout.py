"""One batched episode loop for everything that plays the package's envs: the policy's training rollouts, the
built-in agents when they record datasets, and their reference returns.

LeRobot's own ``rollout`` (lerobot-eval) drives a gymnasium vector env with one reset options dict for all envs
and autoreset; the training rollouts need a reset option per env (a maze layout id each) and the aligned
(s_t, a_t, s_{t+1}) of every step, so the package keeps this loop (evaluation itself is LeRobot's).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import gymnasium as gym

# act(observations of the active envs, their indices in ``envs``) -> one action per active env
Act = Callable[[list[dict], list[int]], Sequence]


@dataclass
class Episode:
    """One played episode: ``observations`` holds s_0 … s_T (the env's dict observations), the other lists one
    entry per step; ``successes[t]`` is ``info["is_success"]`` after step t, ``goals[t]`` its
    ``info["goal_reached"]`` where the env reports one (else ``is_success`` again)."""

    observations: list[dict] = field(default_factory=list)
    actions: list = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)
    successes: list[bool] = field(default_factory=list)
    goals: list[bool] = field(default_factory=list)
    info: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.actions)

    @property
    def total_reward(self) -> float:
        # Added in step order: Python's sum() of floats is compensated and differs in the last bit.
        total = 0.0
        for reward in self.rewards:
            total += reward
        return total

    @property
    def success(self) -> bool:
        """The env's success (what LeRobot's evaluation counts) at some step."""
        return any(self.successes)

    @property
    def goal_reached(self) -> bool:
        """The paper's goal criterion v_e, which the IUPE cycle samples and selects by: the goal was reached at some
        step. Envs whose success is judged at the episode's end (LunarLander: coming to rest on the pad) report
        the goal itself per step as ``info["goal_reached"]``."""
        return any(self.goals)


def run_episodes(
    envs: Sequence[gym.Env], act: Act, seeds: Sequence[int], options: Sequence[dict | None] | None = None
) -> list[Episode]:
    """Play one episode in each env at once, env ``i`` reset with ``seeds[i]`` (and ``options[i]``); at every step
    ``act`` chooses the actions of all envs still running, in env order, so a batched policy runs once a step."""
    options = options or [None] * len(envs)
    episodes = [Episode() for _ in envs]
    for env, episode, seed, option in zip(envs, episodes, seeds, options, strict=True):
        observation, episode.info = env.reset(seed=seed, options=option)
        episode.observations.append(observation)
    active = list(range(len(envs)))
    while active:
        actions = act([episodes[i].observations[-1] for i in active], active)
        still = []
        for i, action in zip(active, actions, strict=True):
            observation, reward, terminated, truncated, info = envs[i].step(action)
            episode = episodes[i]
            episode.observations.append(observation)
            episode.actions.append(action)
            episode.rewards.append(float(reward))
            episode.successes.append(bool(info.get("is_success", False)))
            episode.goals.append(bool(info.get("goal_reached", episode.successes[-1])))
            episode.info = info
            if not (terminated or truncated):
                still.append(i)
        active = still
    return episodes


def agent_act(envs: Sequence[gym.Env], agent: Callable[[gym.Env, dict], int]) -> Act:
    """An ``Act`` for a built-in agent, which acts on one env and observation at a time."""
    return lambda observations, active: [agent(envs[i], obs) for obs, i in zip(observations, active, strict=True)]
