"""Rendering without a display: frames, grids, the latest-output memory, GIF export, the
run-through script and TorchRL's video transforms.

Geometry is checked against positions computed by hand from the world-to-pixel map of each
task's view; colours against Ivy Gym's rule RGB(1 - r, r, 0).
"""
import math

import numpy as np
import pytest
import torch
from PIL import Image

from _env_helpers import REPO, classic_envs, load_script
from torchrl_diffenvs import DiffEnv, make_env
from torchrl_diffenvs.envs import CartPoleEnv
from torchrl_diffenvs.rendering import get_drawer, register_drawer, render_frame, rollout_frames, save_gif
from torchrl_diffenvs.rendering import core as rendering_core

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
    frame_size = 256  # the view (-1.2, 0.6, 0.0, 1.25), widened to a square: 1.8 x 1.8
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


def test_rollout_frames_and_grad_carrying_tensors():
    env = make_env("reacher", num_envs=3, seed=1)
    actions = torch.zeros(3, 2, requires_grad=True)
    rollout = env.rollout(4, lambda td: td.set("action", actions * 1.0), auto_cast_to_device=False)
    assert rollout["next", "reward"].requires_grad
    frames = rollout_frames(env, rollout, env_index=[0, 2], size=48)
    assert len(frames) == 5 and all(f.shape == (48, 96, 3) for f in frames)
    assert np.array_equal(frames[-1], env.render(rollout[:, -1]["next"], env_index=[0, 2], size=48))


# ---------------------------------------------------------------------------- errors and extension
def test_bad_inputs_give_clear_errors():
    env, nxt = stepped("cartpole", num_envs=3)
    with pytest.raises(IndexError, match="out of range for 3 envs"):
        env.render(env_index=3)
    with pytest.raises(ValueError, match="'all'"):
        env.render(env_index="every")
    with pytest.raises(KeyError, match=r"'state' entry.*pass td\['next'\]"):
        env.render(nxt.exclude("state").set("next", nxt))
    with pytest.raises(ValueError, match="rollout_frames"):
        env.render(env.rollout(2))
    with pytest.raises(ValueError, match="size"):
        env.render(size=(0, 10))
    with pytest.raises(KeyError, match="no drawer registered for env 'nope'.*cartpole"):
        get_drawer("nope")


def test_non_finite_state_is_drawn_without_touching_other_envs():
    env, nxt = stepped("swimmer", num_envs=2)
    td = nxt.clone()
    td["state", "pos"][0] = float("nan")
    grid = env.render(td, env_index="all", size=64)
    assert np.array_equal(grid[16:63, 64 + 1 : 127], env.render(nxt, env_index=1, size=64)[16:63, 1:63])
    frame = env.render(td, env_index=0)
    label = frame[:20, :120].astype(int)
    assert ((label[..., 0] > 150) & (label[..., 1] < 90)).sum() > 20, "a red 'non-finite state' label"
    assert count(frame, (102, 153, 255)) > 100, "the goal is still drawn"


class DotEnv(DiffEnv):
    """A point on a line: the smallest task, to show how a new task adds its drawer."""

    name = "dot_for_rendering_test"
    default_params = {"dt": 0.1}

    def initial_state(self, params, n):
        return {"x": self.uniform(-1.0, 1.0, n)}

    def transition(self, state, action, params):
        x = state["x"] + params["dt"] * action[..., 0]
        return {"x": x}, torch.exp(-(x**2)), None

    def observation(self, state, params):
        return state["x"].unsqueeze(-1)


def test_new_task_registers_its_drawer_and_subclasses_inherit_one():
    env = DotEnv(2, seed=0)
    env.reset()
    with pytest.raises(KeyError, match="no drawer registered for env 'dot_for_rendering_test'"):
        env.render()
    try:
        @register_drawer("dot_for_rendering_test", bounds=(-2, 2, -2, 2))
        def draw_dot(canvas, state, params, color):
            canvas.circle((state["x"], 0.0), 0.3, color)

        td = env.reset()
        td["action"] = torch.zeros(2, 1)
        nxt = env.step(td)["next"]
        nxt["reward"] = torch.ones_like(nxt["reward"])
        px, py = centroid(env.render(nxt), GREEN)
        ex, ey = world_to_pixel(nxt["state", "x"][0].item(), 0.0, 2.0)
        assert abs(px - ex) < 1 and abs(py - ey) < 1
        with pytest.raises(ValueError, match="already registered"):
            register_drawer("dot_for_rendering_test", draw_dot, bounds=(-1, 1, -1, 1))
    finally:
        rendering_core._DRAWERS.pop("dot_for_rendering_test", None)

    class MyCartPole(CartPoleEnv):
        name = "my_cartpole_for_rendering_test"

    env = MyCartPole(1, seed=0)
    env.reset()
    assert get_drawer(env) is get_drawer("cartpole")
    assert env.render().shape == (256, 256, 3)


# ---------------------------------------------------------------------------- GIF and run-through
def test_save_gif_round_trip(tmp_path):
    env = make_env("reacher", num_envs=2, seed=0)
    rollout = env.rollout(6, lambda td: td.set("action", torch.ones(2, 2)))
    frames = rollout_frames(env, rollout, env_index="all", size=64)
    path = save_gif(frames, tmp_path / "sub" / "reacher.gif", fps=20)
    with Image.open(path) as gif:
        assert gif.n_frames == len(frames) == 7
        for i, frame in enumerate(frames):
            gif.seek(i)
            assert gif.info["duration"] == 50
            assert np.array_equal(np.asarray(gif.convert("RGB")), frame), f"frame {i} changed"
    with pytest.raises(ValueError, match="no frames"):
        save_gif([], tmp_path / "empty.gif")
    with pytest.raises(ValueError, match=r"frame 1 has shape"):
        save_gif([frames[0], frames[0][:10]], tmp_path / "bad.gif")
    with pytest.raises(TypeError, match="uint8"):
        save_gif([frames[0].astype(np.float32)], tmp_path / "bad.gif")


def load_run_through():
    return load_script("run_through", REPO / "sota_scripts" / "run_through.py")


def test_run_through_script(tmp_path, capsys):
    run_through = load_run_through()
    out = tmp_path / "rt.gif"
    assert run_through.main(["env=reacher", "steps=12", f"out={out}", "seed=3", "fps=25"]) == 0
    assert "End of Run Through Demo!" in capsys.readouterr().out
    with Image.open(out) as gif:
        assert gif.size == (256, 256)
        durations = []
        for i in range(gif.n_frames):
            gif.seek(i)
            durations.append(gif.info["duration"])
    assert sum(durations) == 12 * 40, "12 frames at 25 fps (identical frames are merged, time is kept)"
    # several envs: a grid; running past max_episode_steps (100) auto-resets
    out = tmp_path / "grid.gif"
    run_through.main(["env=cartpole", "steps=105", "num_envs=3", f"out={out}", "size=32"])
    with Image.open(out) as gif:
        assert gif.size == (2 * 32, 2 * 32)
    with pytest.raises(SystemExit, match="env='nope': valid: .*swimmer"):
        run_through.main(["env=nope"])
    with pytest.raises(SystemExit, match="unknown argument 'stepz=3'"):
        run_through.main(["stepz=3"])
    with pytest.raises(SystemExit, match="steps: Value 'many' of type 'str' could not be converted to Integer"):
        run_through.main(["steps=many"])
    with pytest.raises(SystemExit, match="size=0: expected an integer >= 1"):
        run_through.main(["size=0"])


# ---------------------------------------------------------------------------- TorchRL video tooling
@pytest.mark.parametrize("pass_tensordict", [False, True])
def test_torchrl_pixel_render_transform_and_video_recorder(tmp_path, pass_tensordict):
    from torchrl.envs import TransformedEnv
    from torchrl.record import PixelRenderTransform, VideoRecorder
    from torchrl.record.loggers.csv import CSVLogger

    env = make_env("cartpole", num_envs=3, seed=0)
    logger = CSVLogger(exp_name="video", log_dir=str(tmp_path), video_format="pt")
    tenv = TransformedEnv(env, PixelRenderTransform(pass_tensordict=pass_tensordict, env_index="all", size=32))
    tenv.append_transform(VideoRecorder(logger=logger, tag="cartpole"))
    rollout = tenv.rollout(4)
    tenv.transform[-1].dump()
    video = torch.load(tmp_path / "video" / "videos" / "cartpole_0.pt")
    assert video.shape == (1, 5, 3, 64, 64) and video.dtype == torch.uint8  # reset + 4 steps, 2x2 grid
    expected = render_frame(env, rollout[:, -1]["next"], env_index="all", size=32)
    assert np.array_equal(video[0, -1].permute(1, 2, 0).numpy(), expected)
