"""Pictures of the MuJoCo-model tasks.

Geom poses are checked against MuJoCo's own ``geom_xpos``/``geom_xmat``; outlines against sizes
computed by hand from the model files; the picture against the world-to-pixel map of its view.
"""
import importlib

import numpy as np
import pytest
import torch

from torchrl_diffenvs import make_env
from torchrl_diffenvs.envs import MUJOCO_TASKS
from torchrl_diffenvs.rendering import get_drawer, rollout_frames, save_gif
from torchrl_diffenvs.rendering import core as rendering_core
from torchrl_diffenvs.envs.registry import task_spec
from torchrl_diffenvs.rendering.mujoco import MuJoCoView, geom_outlines, geom_world_poses

TASKS = [cls.name for cls in MUJOCO_TASKS]
RED, GREEN = (255, 0, 0), (0, 255, 0)


def count(frame, rgb, tol=0):
    return int((np.abs(frame.astype(float) - np.asarray(rgb, dtype=float)) <= tol).all(-1).sum())


def centroid(frame, rgb):
    ys, xs = np.nonzero((frame == np.asarray(rgb, dtype=np.uint8)).all(-1))
    assert len(xs) > 20, "colour not found in the frame"
    return xs.mean(), ys.mean()


def test_every_mujoco_task_registers_a_view():
    for name in TASKS:
        module, _, attribute = task_spec(name).drawer.partition(":")
        assert module == "torchrl_diffenvs.rendering.mujoco"
        assert isinstance(getattr(importlib.import_module(module), attribute), MuJoCoView), name


@pytest.mark.parametrize("name", TASKS)
def test_geom_poses_match_mujoco(name):
    mujoco = pytest.importorskip("mujoco")
    from torchrl_diffenvs.articulated import gymnasium_asset

    env = make_env(name)
    mm = mujoco.MjModel.from_xml_path(str(gymnasium_asset(env.model_file)))
    data = mujoco.MjData(mm)
    rng = np.random.default_rng(0)
    for _ in range(3):
        data.qpos[:] = mm.qpos0 + rng.uniform(-0.5, 0.5, mm.nq)
        mujoco.mj_kinematics(mm, data)
        pos, rot = geom_world_poses(env.model_file, data.qpos)
        np.testing.assert_allclose(pos, data.geom_xpos, atol=1e-12)
        np.testing.assert_allclose(rot.reshape(-1, 9), data.geom_xmat, atol=1e-12)


def test_outlines_have_the_hand_computed_extent():
    # inverted_pendulum.xml: rail capsule fromto (-1,0,0)-(1,0,0) size 0.02; the pole capsule
    # fromto (0,0,0)-(0.001,0,0.6) size 0.049 1.5, hinged at the cart (slide x)
    outlines = dict(geom_outlines("inverted_pendulum.xml", np.array([0.3, 0.0])))
    rail, pole = outlines[0], outlines[2]
    np.testing.assert_allclose([rail[:, 0].min(), rail[:, 0].max()], [-1.02, 1.02], atol=1e-9)
    np.testing.assert_allclose([rail[:, 1].min(), rail[:, 1].max()], [-0.02, 0.02], atol=1e-9)
    assert pole[:, 1].max() == pytest.approx(0.6 + 0.049, abs=1e-4)
    assert pole[:, 1].min() == pytest.approx(-0.049, abs=1e-4)
    assert (pole[:, 0].min() + pole[:, 0].max()) / 2 == pytest.approx(0.3 + 0.0005, abs=1e-4)  # moved with the cart
    # a side view of the walker gives the floor's height; the top view of reacher its square arena
    assert dict(geom_outlines("hopper.xml", np.r_[0, 1.25, np.zeros(4)]))[0] == 0.0
    arena = dict(geom_outlines("reacher.xml", np.zeros(4), plane="xy"))[0]
    np.testing.assert_allclose(np.abs(arena), 1.0)


@pytest.mark.parametrize("name", TASKS)
def test_every_mujoco_task_renders_coloured_by_reward(name):
    env = make_env(name, num_envs=2, seed=0)
    td = env.reset()
    td["action"] = torch.zeros(2, env.action_dim)
    nxt = env.step(td)["next"]
    frame = env.render()
    assert frame.shape == (256, 256, 3) and frame.dtype == np.uint8
    assert np.array_equal(frame, env.render(nxt))
    low, high = get_drawer(env).reward_range
    for reward, present, absent in ((high, GREEN, RED), (low, RED, GREEN)):
        coloured = nxt.clone()
        coloured["reward"] = torch.full_like(nxt["reward"], reward)
        picture = env.render(coloured)
        assert count(picture, present) > 20 and count(picture, absent) == 0
    assert count(env.render(nxt.exclude("reward")), rendering_core.NO_REWARD_COLOR) > 20


def test_side_view_follows_the_torso_and_fixed_views_do_not():
    # the cart moves 0.5 m: the pole moves 0.5 m in a fixed view of width 2.2 m over 256 pixels
    env = make_env("InvertedPendulum-v5", num_envs=1)
    td = env.reset()
    td["reward"] = torch.ones(1, 1)
    x0, _ = centroid(env.render(td), GREEN)
    td["state", "qpos"][:, 0] += 0.5
    x1, _ = centroid(env.render(td), GREEN)
    assert x1 - x0 == pytest.approx(0.5 * 256 / 2.2, abs=1.5)
    # HalfCheetah moved 5 m forward: the tracking camera keeps its torso in place
    env = make_env("HalfCheetah-v5", num_envs=1)
    td = env.reset()
    td["reward"] = torch.full((1, 1), 5.0)
    before = centroid(env.render(td), GREEN)
    td["state", "qpos"][:, 0] += 5.0
    after = centroid(env.render(td), GREEN)
    np.testing.assert_allclose(after, before, atol=0.5)
    # Hopper's torso lifted 0.3 m: it rises 0.3 m in the picture (its 3 m wide view sets the scale)
    env = make_env("Hopper-v5", num_envs=1)
    td = env.reset()
    td["reward"] = torch.full((1, 1), 4.0)
    _, y0 = centroid(env.render(td), GREEN)
    td["state", "qpos"][:, 1] += 0.3
    _, y1 = centroid(env.render(td), GREEN)
    assert y0 - y1 == pytest.approx(0.3 * 256 / 3.0, abs=1.0)


def test_rollout_gif_of_a_walker(tmp_path):
    env = make_env("Walker2d-v5", num_envs=3, seed=1)
    td = env.rollout(5, auto_reset=True)
    frames = rollout_frames(env, td, env_index=[0, 2], size=64)
    assert len(frames) == 6 and frames[0].shape == (64, 128, 3)
    path = save_gif(frames, tmp_path / "walker.gif")
    assert path.stat().st_size > 0


def test_non_finite_state_draws_a_label_instead_of_raising():
    env = make_env("Hopper-v5", num_envs=2)
    td = env.reset()
    td["state", "qpos"][1] = float("nan")
    healthy, broken = env.render(td, env_index=0), env.render(td, env_index=1)
    assert count(broken, (200, 0, 0), tol=60) > 0 and not np.array_equal(healthy, broken)
