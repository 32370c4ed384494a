"""Rendering without a display: frames, grids, the latest-output memory, GIF export, the
run-through script and TorchRL's video transforms.

Geometry is checked against positions computed by hand from the world-to-pixel map of each
task's view; colours against Ivy Gym's rule RGB(1 - r, r, 0).
"""
import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from _env_helpers import classic_envs
from torchrl_diffenvs import DiffEnv, list_envs, make_env
from torchrl_diffenvs.envs import CartPoleEnv
from torchrl_diffenvs.rendering import get_drawer, register_drawer, render_frame, rollout_frames, save_gif
from torchrl_diffenvs.rendering import core as rendering_core

REPO = Path(__file__).resolve().parents[1]
RED, GREEN = (255, 0, 0), (0, 255, 0)
# rewards that must give a pure green / pure red body (Gymnasium variants map their own ranges)
GREEN_REWARD = {"Pendulum-v1": 0.0, "MountainCarContinuous-v0": 100.0}
RED_REWARD = {"Pendulum-v1": -(math.pi**2 + 0.1 * 64 + 0.001 * 4), "MountainCarContinuous-v0": 0.0}


def stepped(name, num_envs=2, seed=0, **kwargs):
    env = make_env(name, num_envs=num_envs, seed=seed, **kwargs)
    td = env.reset()
    td["action"] = torch.zeros(num_envs, env.action_dim)
    return env, env.step(td)["next"]


def colours(frame):
    return {tuple(c) for c in np.unique(frame.reshape(-1, 3), axis=0).tolist()}


def count(frame, rgb, tol=0):
    return int((np.abs(frame.astype(int) - np.array(rgb)) <= tol).all(-1).sum())


def centroid(frame, rgb):
    ys, xs = np.nonzero((frame == np.array(rgb, dtype=np.uint8)).all(-1))
    assert len(xs) > 0, f"no pixel of colour {rgb}"
    return xs.mean(), ys.mean()


def world_to_pixel(x, y, half_width, size=256, cx=0.0, cy=0.0):
    """Pixel centre coordinates of world (x, y) in a square view of half-width ``half_width``."""
    scale = size / (2 * half_width)
    return (x - cx) * scale + size / 2 - 0.5, size / 2 - (y - cy) * scale - 0.5


def with_state(env, td, **state):
    td = td.clone()
    for key, value in state.items():
        td["state", key] = torch.as_tensor(value, dtype=td["state", key].dtype).expand_as(td["state", key]).clone()
    return td


# ---------------------------------------------------------------------------- every env
@pytest.mark.parametrize("name", classic_envs())
def test_every_env_renders_a_frame_coloured_by_reward(name):
    env, nxt = stepped(name)
    frame = env.render()  # the latest step output
    assert frame.shape == (256, 256, 3) and frame.dtype == np.uint8
    assert len(colours(frame)) >= 5, "frame looks blank"
    assert np.array_equal(frame, env.render(nxt)), "render() must draw the latest step output"

    green = nxt.clone()
    green["reward"] = torch.full_like(nxt["reward"], GREEN_REWARD.get(name, 1.0))
    red = nxt.clone()
    red["reward"] = torch.full_like(nxt["reward"], RED_REWARD.get(name, 0.0))
    frame_green, frame_red = env.render(green), env.render(red)
    assert count(frame_green, GREEN) > 20 and count(frame_green, RED) == 0
    assert count(frame_red, RED) > 20 and count(frame_red, GREEN) == 0
    # halfway between the two rewards: RGB(0.5, 0.5, 0) of Ivy Gym
    half = nxt.clone()
    half["reward"] = torch.full_like(nxt["reward"], (GREEN_REWARD.get(name, 1.0) + RED_REWARD.get(name, 0.0)) / 2)
    assert count(env.render(half), (127.5, 127.5, 0), tol=1) > 20
    # no reward (a reset state): the body is grey, never red or green
    frame_reset = env.render(nxt.exclude("reward"))
    assert count(frame_reset, rendering_core.NO_REWARD_COLOR) > 20 and count(frame_reset, GREEN) == 0


@pytest.mark.parametrize("name", classic_envs())
def test_grid_of_several_envs(name):
    env, nxt = stepped(name, num_envs=5)
    grid = env.render(env_index="all", size=64)
    assert grid.shape == (2 * 64, 3 * 64, 3) and grid.dtype == np.uint8  # 3 columns, 2 rows
    pair = env.render(env_index=[0, 4], size=(40, 50))
    assert pair.shape == (40, 2 * 50, 3)
    # a cell shows the same picture as that env alone (below the label, inside the border)
    alone = env.render(env_index=4, size=64)
    assert np.array_equal(grid[64 + 16 : 127, 64 + 1 : 127], alone[16:63, 1:63])
    assert (grid[64:, 128:] == 255).all(), "the unused sixth cell stays white"


def test_non_square_frames():
    env, _ = stepped("swimmer")
    frame = env.render(size=(100, 180))
    assert frame.shape == (100, 180, 3)


# ---------------------------------------------------------------------------- geometry
def test_cartpole_pole_upright_at_zero_and_leaning_right_for_positive_angle():
    env, nxt = stepped("cartpole", num_envs=1)
    half = get_drawer(env).bounds[1]  # the square view's half-width
    for x, th in [(0.0, 0.0), (1.0, 0.5), (-0.5, -1.2)]:
        td = with_state(env, nxt, x=x, th=th)
        td["reward"] = torch.ones_like(td["reward"])  # green pole
        # the pole's middle is at (x + 0.5 sin th, 0.5 cos th) for a pole of length 1
        px, py = centroid(env.render(td), GREEN)
        ex, ey = world_to_pixel(x + 0.5 * math.sin(th), 0.5 * math.cos(th), half)
        assert abs(px - ex) < 3 and abs(py - ey) < 3, (x, th, (px, py), (ex, ey))


def test_pendulum_rod_points_up_at_zero_and_left_at_half_pi():
    env, nxt = stepped("pendulum", num_envs=1)
    for th in [0.0, math.pi / 2, 2.5]:
        td = with_state(env, nxt, th=th)
        td["reward"] = torch.ones_like(td["reward"])  # green rod
        px, py = centroid(env.render(td), GREEN)
        ex, ey = world_to_pixel(-0.5 * math.sin(th), 0.5 * math.cos(th), 2.2)  # rod middle, view +-2.2
        assert abs(px - ex) < 3 and abs(py - ey) < 3, (th, (px, py), (ex, ey))


def test_reacher_tip_on_goal_when_reward_is_one():
    env, nxt = stepped("reacher", num_envs=1, num_links=3)
    th = torch.tensor([[0.3, 1.2, -0.4]])
    tip = torch.stack([torch.cos(th).sum(-1), torch.sin(th).sum(-1)], -1)
    td = env.reset(with_state(env, nxt, th=th, thd=torch.zeros(1, 3), goal=tip), set_state=True)
    td["action"] = torch.zeros(1, 3)
    nxt = env.step(td)["next"]
    assert nxt["reward"].item() == pytest.approx(1.0)
    frame = env.render()
    px, py = centroid(frame, GREEN)  # the end effector, green at reward 1
    ex, ey = world_to_pixel(*tip[0].tolist(), 3.25)  # view: (links + 0.25) * link_length
    assert abs(px - ex) < 2 and abs(py - ey) < 2


def test_mountaincar_car_on_the_hill_and_flag_at_goal():
    env, nxt = stepped("mountaincar", num_envs=1)
    frame_size, view = 256, (-1.2, 0.6, 0.0, 1.25)  # widened to a square: 1.8 x 1.8
    half, cx, cy = 0.9, -0.3, 0.625
    for x in [-0.9, -0.5, 0.2]:
        td = with_state(env, nxt, x=x)
        td["reward"] = torch.zeros_like(td["reward"])  # red car
        px, py = centroid(env.render(td), RED)
        h = 0.45 * math.sin(3 * x) + 0.55
        slope = math.atan(1.35 * math.cos(3 * x))
        # the body's centre sits 0.0725 above the track, along the track's normal
        ex, ey = world_to_pixel(x - 0.0725 * math.sin(slope), h + 0.0725 * math.cos(slope), half, frame_size, cx, cy)
        assert abs(px - ex) < 2.5 and abs(py - ey) < 2.5, (x, (px, py), (ex, ey))
    goal_blue = (102, 153, 255)
    fx, _ = centroid(env.render(nxt), goal_blue)
    assert world_to_pixel(0.45, 0.0, half, frame_size, cx, cy)[0] < fx < world_to_pixel(0.55, 0, half, frame_size, cx, cy)[0]


def test_swimmer_fish_urchins_and_goal_positions():
    env, nxt = stepped("swimmer", num_envs=1, num_urchins=0)
    td = with_state(env, nxt, pos=torch.tensor([[0.5, -0.6]]), goal=torch.tensor([[-0.7, 0.8]]))
    td["reward"] = torch.ones_like(td["reward"])
    frame = env.render(td)
    fx, fy = centroid(frame, GREEN)
    ex, ey = world_to_pixel(0.5, -0.6, 1.5)
    assert abs(fx - ex) < 4 and abs(fy - ey) < 4  # the tail pulls the centroid back a little
    gx, gy = centroid(frame, (102, 153, 255))
    ex, ey = world_to_pixel(-0.7, 0.8, 1.5)
    assert abs(gx - ex) < 1 and abs(gy - ey) < 1
    assert count(frame, (0, 0, 0)) < 40, "no urchins were asked for (only the fish's eye and outline are black)"
    many, nxt = stepped("swimmer", num_envs=1, num_urchins=9)
    assert count(many.render(nxt), (0, 0, 0)) > count(frame, (0, 0, 0)) + 9 * 50


# ---------------------------------------------------------------------------- latest-output memory
def test_latest_output_is_kept_without_copy_or_graph_and_merged_after_partial_reset():
    env = make_env("pendulum", num_envs=2, seed=0, max_episode_steps=3)
    with pytest.raises(RuntimeError, match="nothing to render yet"):
        env.render()
    td = env.reset()
    kept = env._render_source["state"]["th"]
    assert kept.data_ptr() == td["state", "th"].data_ptr(), "no copy of the state"
    td["episode_step"][0] = 1  # env 0 is truncated one step before env 1
    td["action"] = torch.ones(2, 1)
    td, td_next = env.step_and_maybe_reset(td)
    td_next["action"] = torch.ones(2, 1)
    td, td_next = env.step_and_maybe_reset(td_next)
    assert td["next", "done"].view(-1).tolist() == [True, False]
    # env 0 was auto-reset: the latest state is the fresh one (no reward yet, grey);
    # env 1 was not: its latest state is the post-step one, coloured by its reward
    assert np.array_equal(env.render(env_index=0), env.render(td_next, env_index=0))
    assert np.array_equal(env.render(env_index=1), env.render(td["next"], env_index=1))
    assert not np.array_equal(env.render(env_index=1), env.render(td_next, env_index=1))


def test_the_env_does_not_keep_a_rollouts_graph_alive():
    """After a differentiable rollout, the env's render memory holds no autograd graph: once the
    caller drops the rollout, the tensors the graph saved for backward are freed (watched weakly)."""
    import gc
    import weakref

    env = make_env("pendulum", num_envs=4, seed=0)
    action = torch.zeros(4, 1, requires_grad=True)
    saved = []  # weak references to tensors that only the graph holds

    def policy(td):
        gain = torch.full((4, 1), 0.5)  # saved by the multiplication for the backward pass
        saved.append(weakref.ref(gain))
        return td.set("action", action * gain)

    for run in (lambda: env.rollout(5, policy), lambda: env.step(policy(env.reset()))):
        saved.clear()
        out = run()
        assert out["next", "reward"].requires_grad and saved and all(ref() is not None for ref in saved)
        kept = env._render_source
        assert not any(v.requires_grad for v in kept["state"].values()) and not kept["reward"].requires_grad
        del out
        gc.collect()
        assert all(ref() is None for ref in saved), "the env still holds the rollout's graph"
        env.render()  # drawing the latest output still works
