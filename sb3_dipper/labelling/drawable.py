"""Which envs the labelling page can draw, decided without drawing a picture.

:class:`~sb3_dipper.labelling.render.PairRenderer` picks how to draw a pair with :func:`drawing_of`, and training checks
its env with :func:`why_page_cannot_draw` when a label queue is set up
(:func:`~sb3_dipper.labelling.preference_source_from`), so that a run whose pairs nobody could see is refused before it
starts. Both make the env the same way (:func:`make_render_env`). This module needs no matplotlib, which only the
``label`` extra installs: training without the page checks its env all the same.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
from gymnasium_robotics.envs.fetch import MujocoFetchEnv
from gymnasium_robotics.envs.franka_kitchen import KitchenEnv
from gymnasium_robotics.envs.maze.maze import Maze as MazeBeforeV4
from gymnasium_robotics.envs.maze.maze_v4 import Maze

# How the page draws a pair (sb3_dipper.labelling.render): a top-down view of the maze, or a strip of frames.
MAZE = "maze"
FETCH = "fetch"
KITCHEN = "kitchen"
# What the page draws, for messages.
DRAWN_ENVS = "gymnasium-robotics mazes (PointMaze, AntMaze), MuJoCo Fetch tasks and Franka Kitchen tasks"


def make_render_env(env_id: str, env_kwargs: dict[str, Any]) -> gym.Env:
    """The env the page draws with: ``env_id`` made with ``env_kwargs`` and ``render_mode="rgb_array"``, reset.

    :param env_id: a registered env id (ours and gymnasium-robotics' are registered here)
    :param env_kwargs: the keyword arguments the training env was made with
    """
    import gymnasium_robotics

    import sb3_dipper  # noqa: F401  (registers our env ids)

    gym.register_envs(gymnasium_robotics)
    env = gym.make(env_id, **{**env_kwargs, "render_mode": "rgb_array"})
    try:
        env.reset(seed=0)
    except BaseException:
        env.close()
        raise
    return env


def drawing_of(unwrapped: gym.Env) -> str:
    """How the page draws the pairs of an env: :data:`MAZE`, :data:`FETCH` or :data:`KITCHEN`.

    :param unwrapped: the env without its wrappers (``env.unwrapped``)
    :raises ValueError: the page cannot draw this env (the message says why)
    """
    name = type(unwrapped).__name__
    maze = getattr(unwrapped, "maze", None)
    if maze is not None:
        if isinstance(maze, (Maze, MazeBeforeV4)):
            return MAZE
        # The Fetch maze: a strip of frames would show the walls of the reset's layout, not those of the pair's episode.
        raise ValueError(f"{name}'s maze is not a gymnasium-robotics maze map, the only maze whose walls the page draws")
    if isinstance(unwrapped, KitchenEnv):
        return KITCHEN
    # The frames put the achieved goal back with mujoco's bindings, which mujoco-py's Fetch envs do not use.
    if isinstance(unwrapped, MujocoFetchEnv):
        return FETCH
    raise ValueError(f"{name} is not a kind of env the page draws")


def why_page_cannot_draw(info: dict[str, Any]) -> str | None:
    """Why the page cannot draw the pairs of the env a label queue records (``queue.json``); ``None`` if it can.

    The env is made as the page makes it, and asked :func:`drawing_of`; no frame is rendered.

    :param info: the queue's ``queue.json`` content (``env_id``, ``env_kwargs``)
    """
    env_id = info.get("env_id")
    if not env_id:
        return "it has no registered id to make the page's own copy of the env from (env.spec is None)"
    try:
        env = make_render_env(str(env_id), dict(info.get("env_kwargs") or {}))
    except Exception as error:  # a user's env fails in its own ways: gymnasium's NameNotFound, a TypeError, ...
        return f"gymnasium.make({env_id!r}, render_mode='rgb_array') failed: {type(error).__name__}: {error}"
    try:
        drawing_of(env.unwrapped)
    except ValueError as error:
        return str(error)
    finally:
        env.close()
    return None
