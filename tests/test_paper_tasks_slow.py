"""DIPPER on the paper's tasks at their CPU profiles: opt-in learning checks (`make test-slow`).

Measured (BENCHMARKS.md, "the paper's tasks on a CPU"): on `FetchPickAndPlaceFixed-v0`, every seed-0 run of DIPPER at
the CPU profile (the paper's configuration, with clipped lower targets, without the Q-filter, and with the maze's
switches, the hyperparams/dipper.yml entry) solved the task at the 15k or 30k evaluation, while the untrained policy, flat
SAC+HER and HIER never did. The solution does not last on every configuration and seeds 1-2 reach it late or not at all,
so this checks that learning happens (the demonstration teaches the grasp), not the paper's final success rate. The
task is deterministic, so an evaluation is all or nothing. The other paper tasks have no measured learning signal at a
CPU budget yet, so they have no check here.
"""

import sys
from pathlib import Path

import numpy as np
import pytest
from stable_baselines3.common.callbacks import BaseCallback

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "zoo_scripts"))
from configs import episode_successes, load_entry, make_env, make_model

PICK_AND_PLACE = "FetchPickAndPlaceFixed-v0"


class SuccessEvery(BaseCallback):
    """Deterministic success over a few episodes every ``freq`` primitive steps."""

    def __init__(self, eval_env, freq: int, n_episodes: int):
        super().__init__()
        self.eval_env, self.freq, self.n_episodes = eval_env, freq, n_episodes
        self.successes: list[float] = []

    def _on_step(self) -> bool:
        if self.num_timesteps % self.freq < self.model.n_envs:
            self.successes.append(float(np.mean(episode_successes(self.model, self.eval_env, self.n_episodes))))
        return True


@pytest.mark.slow
def test_dipper_learns_to_pick_and_place_from_its_one_demonstration():
    model, _, _ = make_model("dipper", PICK_AND_PLACE, seed=0)
    eval_env = make_env(PICK_AND_PLACE, load_entry("dipper", PICK_AND_PLACE), seed=10_000, n_envs=2)
    untrained = float(np.mean(episode_successes(model, eval_env, 4)))
    callback = SuccessEvery(eval_env, freq=15_000, n_episodes=4)
    model.learn(45_000, callback=callback)
    assert untrained == 0.0
    assert max(callback.successes) == 1.0, callback.successes
