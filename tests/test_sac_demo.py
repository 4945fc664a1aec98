"""SACDemo: SB3's SAC without demonstrations; with them, the hierarchies' Q-filtered cloning on the env's own goals."""

import shutil

import numpy as np
import pytest
import torch as th
from stable_baselines3 import SAC, HerReplayBuffer
from stable_baselines3.common.logger import configure
from stable_baselines3.common.vec_env import VecNormalize

from sb3_dipper import SACDemo
from sb3_dipper.common.demonstrations import load_demonstrations
from sb3_dipper.common.imitation import DEFAULT_DEMO_KWARGS
from sb3_dipper.common.validation import InvalidSetting
from sb3_dipper.envs.demos import expert_demonstrations
from tests.conftest import short_maze
from tests.test_save_load import rollout_actions

MAZE = "PointMazeFourRooms-v0"
SAC_DEMO_DEFAULTS = {key: value for key, value in DEFAULT_DEMO_KWARGS.items() if key != "normalize_from_demos"}
TINY = dict(
    replay_buffer_class=HerReplayBuffer,
    learning_starts=40,
    buffer_size=2000,
    batch_size=16,
    policy_kwargs=dict(net_arch=[16]),
    seed=0,
)


@pytest.fixture(scope="module")
def maze_demos(tmp_path_factory):
    path = tmp_path_factory.mktemp("demos") / "maze.npz"
    expert_demonstrations(MAZE, n_episodes=2, seed=0).save(path)
    return path


def test_without_demonstrations_it_trains_as_sb3s_sac():
    flat = SACDemo("MultiInputPolicy", short_maze(seed=3), **TINY).learn(200)
    sac = SAC("MultiInputPolicy", short_maze(seed=3), **TINY).learn(200)
    assert flat.demonstrations is None
    ours, theirs = flat.policy.state_dict(), sac.policy.state_dict()
    assert ours.keys() == theirs.keys() and all(th.equal(ours[name], theirs[name]) for name in ours)


def test_the_demonstrations_are_flat_transitions_with_the_envs_goals_and_reward(maze_demos):
    """Goals are the env's desired goal or a goal the episode achieved later (whole achieved goals, no subgoal
    projection), rewarded by the env's compute_reward; actions are in the policy's [-1, 1] scale."""
    env = short_maze()
    model = SACDemo("MultiInputPolicy", env, demo_kwargs=dict(demo_path=str(maze_demos), n_demos=2), **TINY)
    buffer = model.demonstrations
    assert buffer is not None and len(buffer) == 400
    np.testing.assert_array_equal(buffer.desired, load_demonstrations(maze_demos).observations["desired_goal"])
    np.random.seed(0)
    observations, actions, next_observations, rewards = buffer.sample(500)
    for row in range(500):
        step = int(np.flatnonzero(np.all(buffer.observation == observations["observation"][row], axis=1))[0])
        goal = observations["desired_goal"][row]
        later = buffer.next_achieved[step : buffer.last_step[step] + 1]
        assert np.any(np.all(later == goal, axis=1)) or np.array_equal(goal, buffer.desired[step])
    expected = env.env_method("compute_reward", next_observations["achieved_goal"], observations["desired_goal"], [{}] * 500)
    np.testing.assert_array_equal(rewards, np.asarray(expected[0], dtype=np.float32))
    assert rewards.dtype == np.float32 and 0 < -rewards.sum() < 500
    assert np.all(np.abs(actions) <= 1.0)


def actor_error(model: SACDemo) -> float:
    """Mean squared distance between the deterministic actor's actions and the demonstrated ones on the demo states."""
    buffer = model.demonstrations
    observations = {"observation": buffer.observation, "achieved_goal": buffer.achieved, "desired_goal": buffer.desired}
    with th.no_grad():
        actions = model.actor(model.policy.obs_to_tensor(observations)[0], deterministic=True).numpy()
    return float(((actions - buffer.actions) ** 2).sum(axis=1).mean())


def test_the_cloning_loss_moves_the_actor_to_the_demonstrated_actions(maze_demos, tmp_path):
    """With the cloning weight large and SAC's actor loss off, the actor's update is the cloning alone."""
    model = SACDemo(
        "MultiInputPolicy",
        short_maze(),
        demo_kwargs=dict(demo_path=str(maze_demos), bc_coef=10.0, rl_coef=0.0, q_filter=False, demo_share=0.5),
        replay_buffer_class=HerReplayBuffer,
        learning_starts=40,
        learning_rate=1e-3,
        buffer_size=2000,
        policy_kwargs=dict(net_arch=[64, 64]),
        seed=0,
    )
    model.learn(40)  # an episode in the buffer, no update yet
    model.set_logger(configure(str(tmp_path), ["csv"]))
    before = actor_error(model)
    model.train(gradient_steps=300, batch_size=64)
    after = actor_error(model)
    assert after < 0.25 * before, (before, after)
    model.logger.dump(0)
    header = open(tmp_path / "progress.csv").readline().strip().split(",")
    assert {"train/bc_loss", "train/q_filter_kept"} <= set(header)


def test_without_cloning_weight_the_demonstrations_do_not_move_the_actor(maze_demos):
    """The control: bc_coef = 0 and rl_coef = 0 leave the actor as it was (only the critics learn)."""
    demo_kwargs = dict(demo_path=str(maze_demos), bc_coef=0.0, rl_coef=0.0)
    model = SACDemo("MultiInputPolicy", short_maze(), demo_kwargs=demo_kwargs, **TINY)
    model.learn(40)
    actor = {name: tensor.clone() for name, tensor in model.actor.state_dict().items()}
    model.train(gradient_steps=20, batch_size=16)
    assert all(th.equal(actor[name], tensor) for name, tensor in model.actor.state_dict().items())


def test_demonstration_rows_are_normalised_as_the_replay_rows():
    env = VecNormalize(short_maze(), norm_reward=True)
    model = SACDemo("MultiInputPolicy", env, demo_kwargs=dict(demo_path="auto"), **TINY)
    model.learn(100)
    fixed = model.demonstrations.sample(8)
    model.demonstrations.sample = lambda n_demo: fixed
    batch = model._mixed_batch(8, 8)
    expected = env.normalize_obs(fixed[0])
    for key in expected:
        np.testing.assert_allclose(batch.observations[key][-8:].numpy(), expected[key], rtol=1e-6)
    rewards = batch.rewards[-8:, 0].numpy()
    np.testing.assert_allclose(rewards, env.normalize_reward(fixed[3]), rtol=1e-6)
    assert not np.allclose(rewards, fixed[3]), "the reward statistics have moved from 1 by now"


def test_loading_reads_the_demonstrations_again_only_with_an_env(tmp_path):
    model = SACDemo("MultiInputPolicy", short_maze(), demo_kwargs=dict(demo_path="auto", bc_coef=0.02), **TINY)
    model.learn(60)
    model.save(tmp_path / "model.zip")
    assert SACDemo.load(tmp_path / "model.zip").demonstrations is None
    loaded = SACDemo.load(tmp_path / "model.zip", env=short_maze(seed=1))
    assert loaded.demo_kwargs == model.demo_kwargs and loaded.bc_coef == 0.02
    assert len(loaded.demonstrations) == len(model.demonstrations)
    np.testing.assert_array_equal(loaded.demonstrations.actions, model.demonstrations.actions)
    loaded.learn(60, reset_num_timesteps=False)
    assert loaded.num_timesteps == 120
    # demo_kwargs given to load change the keys they name, as the hierarchies'.
    reloaded = SACDemo.load(tmp_path / "model.zip", env=short_maze(seed=1), demo_kwargs={"demo_share": 0.5})
    assert reloaded.demo_kwargs == {**model.demo_kwargs, "demo_share": 0.5} and reloaded.demonstrations is not None


def test_demo_kwargs_are_the_hierarchies_but_normalize_from_demos_checked_as_theirs(maze_demos):
    demo_kwargs = dict(demo_path=str(maze_demos), n_demos="1.0", bc_coef="1e-2")
    model = SACDemo("MultiInputPolicy", short_maze(), demo_kwargs=demo_kwargs, **TINY)
    assert model.demo_kwargs == {**SAC_DEMO_DEFAULTS, "demo_path": str(maze_demos), "n_demos": 1, "bc_coef": 0.01}
    assert type(model.demo_kwargs["n_demos"]) is int
    # The update reads DemoSAC's attributes, which read and write demo_kwargs: one place for each setting.
    assert model.bc_coef == 0.01
    model.q_filter = False
    assert model.demo_kwargs["q_filter"] is False
    model.demo_kwargs["rl_coef"] = 0.5
    assert model.rl_coef == 0.5
    with pytest.raises(
        TypeError, match=r"^demo_kwargs got an unexpected key 'normalize_from_demos'; its keys are demo_path, "
    ):
        SACDemo("MultiInputPolicy", short_maze(), demo_kwargs=dict(normalize_from_demos=True), **TINY)
    with pytest.raises(ValueError, match=r"demo_kwargs\['demo_share'\] must be a finite number in \[0, 1\]"):
        SACDemo("MultiInputPolicy", short_maze(), demo_kwargs=dict(demo_share=1.5), **TINY)
    with pytest.raises(
        TypeError, match=r"SACDemo got an unexpected keyword argument 'demo_path'; did you mean 'demo_kwargs'\?"
    ):
        SACDemo("MultiInputPolicy", short_maze(), demo_path=str(maze_demos), **TINY)


def test_a_predict_only_model_asks_for_an_env_to_learn(tmp_path):
    SACDemo("MultiInputPolicy", short_maze(), **TINY).save(tmp_path / "model.zip")
    with pytest.raises(ValueError, match=r"loaded without an env, only to predict: .*set_env"):
        SACDemo.load(tmp_path / "model.zip").learn(10)


@pytest.mark.parametrize(("setting", "value"), [("n_steps", 3), ("use_sde", True)])
def test_settings_the_cloning_update_cannot_honour_are_refused_with_demonstrations(setting, value):
    with pytest.raises(
        InvalidSetting, match=rf"^{setting}=.* with a demo_path: .*leave demo_kwargs\['demo_path'\] out"
    ) as error:
        SACDemo("MultiInputPolicy", short_maze(), demo_kwargs=dict(demo_path="auto"), **{setting: value}, **TINY)
    assert error.value.setting == setting


def test_a_non_goal_env_is_refused():
    with pytest.raises(ValueError, match="SACDemo needs a goal-conditioned env"):
        SACDemo("MlpPolicy", "Pendulum-v1")


def test_a_set_env_refused_for_moved_demonstrations_keeps_the_trained_networks(tmp_path, maze_demos):
    """A model loaded without an env is rebuilt by set_env; the demonstrations gone, it keeps its trained networks."""
    demo_path = shutil.copy(maze_demos, tmp_path / "demos.npz")
    model = SACDemo("MultiInputPolicy", short_maze(), demo_kwargs=dict(demo_path=str(demo_path)), **TINY)
    model.learn(100)
    model.save(tmp_path / "model")
    loaded = SACDemo.load(tmp_path / "model")
    actions = rollout_actions(loaded, short_maze(seed=4))
    shutil.move(demo_path, tmp_path / "moved.npz")
    with pytest.raises(FileNotFoundError, match=r"demos\.npz"):
        loaded.set_env(short_maze(seed=1))
    np.testing.assert_array_equal(rollout_actions(loaded, short_maze(seed=4)), actions)
