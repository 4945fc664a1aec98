"""Every algorithm runs, acts, logs and works with SB3's callbacks, evaluation and VecNormalize (as SB3's test_run.py
and test_predict.py). What only one algorithm does is tested in its own file (tests/test_<algorithm>.py)."""

import os

import numpy as np
import pytest
from stable_baselines3.common.callbacks import BaseCallback, CheckpointCallback, EvalCallback
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.logger import configure
from stable_baselines3.common.vec_env import SubprocVecEnv, VecNormalize

from sb3_dipper import DAC, DIPPER, HAC, HIER, PIPER, RAPS, SAGA, DPOFlat, SACDemo
from tests.conftest import ALL_ALGORITHMS, HIERARCHICAL_ALGORITHMS, OPTION_ALGORITHMS, any_tiny_model, short_maze, tiny_model


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
@pytest.mark.parametrize("policy", ["MlpPolicy", "MultiInputPolicy"])
def test_learn_then_predict_a_primitive_action(model_class, policy, maze_env):
    model = any_tiny_model(model_class, maze_env, policy=policy)
    model.learn(120)
    assert model.num_timesteps >= 120
    obs = maze_env.reset()
    action, state = model.predict(obs, deterministic=True)
    assert action.shape == (1, 2) and np.all(np.abs(action) <= 1.0)
    if model_class in OPTION_ALGORITHMS:
        # The option's higher action (a subgoal; RAPS: a primitive's arguments and selector) and its steps left.
        higher_actions, steps_left = state
        assert higher_actions.shape == (1, *model.policy.action_space.shape) and steps_left.tolist() == [4]
    else:
        assert state is None


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_two_envs_in_subprocesses(model_class):
    # Forked workers: what differs per algorithm is its side of the pipes. SB3's default start method (forkserver, whose
    # workers import everything anew, seconds each) runs in the zoo's `--vec-env subproc` test.
    env = short_maze(n_envs=2, vec_env_cls=SubprocVecEnv, vec_env_kwargs=dict(start_method="fork"))
    try:
        model = any_tiny_model(model_class, env)
        model.learn(160, progress_bar=True)
        assert model.num_timesteps == 160
        action, _ = model.predict(env.reset(), deterministic=False)
        assert action.shape == (2, 2)
    finally:
        env.close()


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_predict_on_an_unbatched_observation_and_state_handover(model_class, maze_env):
    model = any_tiny_model(model_class, maze_env)
    env = maze_env.envs[0]
    obs, _ = env.reset(seed=3)
    action, state = model.predict(obs, deterministic=True)
    assert action.shape == (2,) and env.action_space.contains(action.astype(np.float32))
    if model_class not in OPTION_ALGORITHMS:
        assert state is None
        return
    higher_action = state[0].copy()
    for steps_left in (3, 2, 1, 0):
        obs, *_ = env.step(action)
        action, state = model.predict(obs, state=state, deterministic=True)
        np.testing.assert_array_equal(state[0], higher_action)
        assert state[1].tolist() == [steps_left]
    obs, *_ = env.step(action)
    _, state = model.predict(obs, state=state, deterministic=True)
    assert state[1].tolist() == [4]
    _, restarted = model.predict(obs, state=state, episode_start=np.array([True]), deterministic=True)
    assert restarted[1].tolist() == [4]


def test_every_primitive_transition_reaches_the_lower_buffer_once():
    env = short_maze(n_envs=2)
    model = tiny_model(DIPPER, env, learning_starts=10_000)
    model.learn(100)
    buffer = model.lower.replay_buffer
    assert model.num_timesteps == 100 and buffer.pos == 50
    # Stored transitions chain within each lower segment: next observation of step i is the observation of step i+1.
    for env_idx in range(2):
        observations = buffer.observations["observation"][:50, env_idx]
        next_observations = buffer.next_observations["observation"][:50, env_idx]
        segment_ends = buffer.dones[:50, env_idx].astype(bool)
        np.testing.assert_allclose(next_observations[:-1][~segment_ends[:-1]], observations[1:][~segment_ends[:-1]])
        assert segment_ends.sum() == 10  # 50 steps of 5-step segments


class CountSteps(BaseCallback):
    def _on_step(self) -> bool:
        assert "dones" in self.locals and "infos" in self.locals
        return True


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_callbacks_run_once_per_primitive_step(model_class, tmp_path):
    env = short_maze(n_envs=2)
    counter = CountSteps()
    eval_callback = EvalCallback(
        short_maze(seed=5), n_eval_episodes=2, eval_freq=40, log_path=str(tmp_path), best_model_save_path=str(tmp_path)
    )
    checkpoint = CheckpointCallback(save_freq=50, save_path=str(tmp_path), save_replay_buffer=True)
    model = any_tiny_model(model_class, env)
    model.learn(200, callback=[counter, eval_callback, checkpoint], progress_bar=True)
    assert counter.n_calls == 100
    evaluations = np.load(tmp_path / "evaluations.npz")
    assert evaluations["timesteps"].tolist() == [80, 160] and evaluations["successes"].shape == (2, 2)
    assert (tmp_path / "best_model.zip").exists() and (tmp_path / "rl_model_100_steps.zip").exists()
    # SB3 saves a replay buffer only where the model has one; DPO-FLAT keeps episodes, which its own files hold.
    assert (tmp_path / "rl_model_replay_buffer_100_steps.pkl").exists() == (model_class is not DPOFlat)


class StopAfter(BaseCallback):
    def __init__(self, calls: int):
        super().__init__()
        self.calls = calls

    def _on_step(self) -> bool:
        return self.n_calls < self.calls


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_a_callback_can_stop_training_mid_option(model_class, maze_env):
    model = any_tiny_model(model_class, maze_env)
    model.learn(1000, callback=StopAfter(13))
    assert model.num_timesteps == 13
    model.learn(20)  # the interrupted option leaves nothing open that breaks a new run
    assert model.num_timesteps == 20


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_evaluate_policy(model_class, maze_env):
    model = any_tiny_model(model_class, maze_env)
    mean_reward, _ = evaluate_policy(model, short_maze(seed=9), n_eval_episodes=3, deterministic=True)
    assert -20.0 <= mean_reward <= 0.0


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_vec_normalize(model_class):
    # RAPS's primitives read positions from the observation, so it takes VecNormalize without observation normalisation
    # (tests/test_raps.py: it refuses norm_obs=True).
    norm_obs = model_class is not RAPS
    env = VecNormalize(short_maze(), norm_obs=norm_obs, norm_reward=not norm_obs)
    model = any_tiny_model(model_class, env)
    model.learn(120)
    if model_class in HIERARCHICAL_ALGORITHMS:
        assert model.low_normalizer is not None and "achieved_goal" in model.low_normalizer.statistics
        np.testing.assert_allclose(
            model.low_normalizer.statistics["achieved_goal"][0], env.obs_rms["achieved_goal"].mean, atol=1e-6
        )
    env.training = False
    mean_reward, _ = evaluate_policy(model, env, n_eval_episodes=2)
    assert np.isfinite(mean_reward)


# The keys every run logs, then each algorithm's own: both levels' losses for a hierarchy (train/low_*, train/high_*).
COMMON_LOG_KEYS = {"rollout/success_rate", "time/fps", "time/total_timesteps"}
OPTION_LOG_KEYS = {"rollout/subgoal_distance", "rollout/low_value", "train/low_actor_loss", "train/low_critic_loss"}
OPTION_LOG_KEYS |= {"train/low_ent_coef"}
HIGHER_SAC_LOG_KEYS = {"train/high_actor_loss", "train/high_critic_loss"}
LOG_KEYS = {
    DIPPER: OPTION_LOG_KEYS | {"train/high_dpo_loss", "train/high_preference_pairs"},
    HIER: OPTION_LOG_KEYS | HIGHER_SAC_LOG_KEYS,
    PIPER: OPTION_LOG_KEYS
    | HIGHER_SAC_LOG_KEYS
    | {"train/high_reward_model_loss", "train/high_reward_model_accuracy", "train/high_preference_pairs"},
    SAGA: OPTION_LOG_KEYS | HIGHER_SAC_LOG_KEYS | {"train/high_disc_loss", "train/high_adversarial_loss"},
    HAC: OPTION_LOG_KEYS | HIGHER_SAC_LOG_KEYS | {"train/high_target_q", "rollout/tested_subgoal_missed"},
    RAPS: HIGHER_SAC_LOG_KEYS,
    DAC: {"train/actor_loss", "train/critic_loss", "train/disc_loss", "train/disc_expert_accuracy"}
    | {"train/disc_policy_accuracy", "train/gradient_penalty", "train/disc_reward"},
    DPOFlat: {"rollout/ep_len_mean", "train/dpo_loss", "train/preference_pairs", "train/pref_accuracy", "train/n_updates"},
    SACDemo: {"train/actor_loss", "train/critic_loss", "train/ent_coef", "train/bc_loss", "train/q_filter_kept"},
}


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_log_keys(model_class, tmp_path):
    model = any_tiny_model(model_class, short_maze())
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(200, log_interval=1)
    header = set(open(os.path.join(tmp_path, "progress.csv")).readline().strip().split(","))
    assert COMMON_LOG_KEYS | LOG_KEYS[model_class] <= header
    if model_class in OPTION_ALGORITHMS:
        assert "train/actor_loss" not in header  # each level's losses under its own name


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(switch_kwargs=dict(value_reg="score")),
        dict(switch_kwargs=dict(value_reg="reparam")),
        dict(
            switch_kwargs=dict(nll_coef=1.0, hindsight_actions=True, truncate_at_goal=True),
            policy_kwargs=dict(net_arch=[16], acting_tau=0.05),
        ),
        dict(value_reg_coef=0.0),
    ],
)
def test_dipper_switches_run(kwargs, maze_env, tmp_path):
    model = tiny_model(DIPPER, maze_env, **kwargs)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(200, log_interval=1)
    assert len(model.preferences) > 0


def test_hier_and_dipper_share_the_option_layer(maze_env):
    for model_class in (DIPPER, HIER):
        model = tiny_model(model_class, maze_env)
        assert model.option_env is not None and model.option_env.option_steps == 5
