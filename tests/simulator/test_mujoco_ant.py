"""Ant-v5 (a free joint and smooth 3-D ground contact) against gymnasium's own Ant-v5 and by hand.

In the air (no contact) the dynamics, observations (105 entries, contact forces 0), rewards and
termination equal gymnasium's; on the ground the contact forces are the smooth model's, so the
``cfrc_ext`` entries are checked against the generalised contact force on the free joint instead.
"""
import numpy as np
import pytest
import torch

from torchrl_diffenvs.articulated.dynamics import contact_force, forward_kinematics
from torchrl_diffenvs.envs import make_env
from _env_helpers import with_smooth_contact  # noqa: E402

# written for the smooth contact option (MuJoCo's own: tests/simulator/test_mujoco_contact.py)
make_env = with_smooth_contact(make_env)

gym = pytest.importorskip("gymnasium")
pytest.importorskip("mujoco")


def test_ant_in_the_air_matches_gymnasium():
    """Dropped from 8 m, 20 steps (1 s) of random actions: observation, reward, terminated
    (healthy range widened to (0.2, 10) in both, so the flight counts as healthy), to 1e-9: the
    file's RK4 as MuJoCo 4's, its rotation correction included."""
    genv = gym.make("Ant-v5", healthy_z_range=(0.2, 10.0))
    env = make_env("Ant-v5", num_envs=1, dtype=torch.float64, seed=0, params={"healthy_z_high": 10.0},
                   integrator="model")  # gymnasium runs the file's RK4
    gobs, _ = genv.reset(seed=0)
    data = genv.unwrapped.data
    qpos, qvel = data.qpos.copy(), data.qvel.copy()
    qpos[2] = 8.0
    genv.unwrapped.set_state(qpos, qvel)
    td = env.reset()
    td["state", "qpos"], td["state", "qvel"] = torch.tensor(qpos[None]), torch.tensor(qvel[None])
    td["state", "torso_xy"] = torch.tensor(qpos[None, :2])
    td = env.reset(td, set_state=True)
    gobs = genv.unwrapped._get_obs()
    assert gobs.shape == (105,) and td["observation"].shape == (1, 105)
    np.testing.assert_allclose(td["observation"][0].numpy(), gobs, atol=1e-12)
    rng = np.random.default_rng(0)
    for _ in range(20):
        action = rng.uniform(-1, 1, size=8)
        gobs, greward, gterm, gtrunc, info = genv.step(action)
        td["action"] = torch.tensor(action[None])
        nxt = env.step(td)["next"]
        np.testing.assert_allclose(nxt["observation"][0].numpy(), gobs, atol=1e-9, rtol=1e-9)
        assert nxt["reward"].item() == pytest.approx(greward, abs=1e-9)
        assert abs(info["x_velocity"]) > 1e-3  # the forward term is exercised
        assert nxt["terminated"].item() == gterm is False
        td = nxt.clone()
    assert 2.0 < td["state", "qpos"][0, 2].item() < 8.0  # still falling, never touched the floor


def test_ant_observation_options():
    kinds = {(True, True): 105, (True, False): 27, (False, True): 107, (False, False): 29}
    for (exclude, include), size in kinds.items():
        env = make_env("Ant-v5", num_envs=2, exclude_current_positions_from_observation=exclude,
                       include_cfrc_ext_in_observation=include)
        assert env.reset()["observation"].shape == (2, size)
        gym_size = gym.make("Ant-v5", exclude_current_positions_from_observation=exclude,
                            include_cfrc_ext_in_observation=include).observation_space.shape
        assert gym_size == (size,)


def test_ant_contact_forces_are_the_floors_wrench_on_each_body():
    """``cfrc_ext`` on the ground: summed over the bodies, its force is the generalised contact
    force on the free joint's translation (world frame), and its torque about the centre of mass,
    moved to the torso origin, is the force on the free joint's rotation (torso frame). The
    observation clips it to [-1, 1] and the contact cost is 5e-4 times its clipped square."""
    env = make_env("Ant-v5", num_envs=3, dtype=torch.float64, seed=0)
    td = env.reset()
    td["action"] = torch.zeros(3, 8, dtype=torch.float64)
    for _ in range(20):  # fall onto the floor and settle (1 s)
        td = env.step(td)["next"].clone()
        td["action"] = torch.zeros(3, 8, dtype=torch.float64)
    state, params = td["state"], env.params
    # the stored wrench belongs to the last physics stage: recompute it at the final state to compare
    qpos, qvel = state["qpos"], state["qvel"]
    wrench = env.contact_wrenches(qpos, qvel, td["action"], params)
    kin = forward_kinematics(env.tree, qpos)
    generalised = contact_force(env.tree, kin, qvel, params)
    total = wrench.sum(1)
    assert total[:, 5].min() > 1.0  # the floor carries the Ant (weight 8.9 N)
    torch.testing.assert_close(total[:, 3:], generalised[:, :3])
    mass = params["body_mass"]
    com = kin.body_pos + (kin.body_rot @ env.tree.body_com.unsqueeze(-1)).squeeze(-1)
    centre = (mass.unsqueeze(-1) * com).sum(1) / mass.sum(1, keepdim=True)
    torso = qpos[:, :3]
    torque_at_torso = total[:, :3] + torch.linalg.cross(centre - torso, total[:, 3:])
    rot = kin.body_rot[:, 1]
    torch.testing.assert_close((rot.transpose(-1, -2) @ torque_at_torso.unsqueeze(-1)).squeeze(-1), generalised[:, 3:6])
    assert wrench[:, 0].abs().max() == 0  # the world body gets nothing (as MuJoCo's cfrc_ext)
    # observation and contact cost from the stored (last-stage) wrench
    clipped = state["cfrc_ext"].clamp(-1.0, 1.0)
    torch.testing.assert_close(td["observation"][:, 27:], clipped[:, 1:].flatten(1))
    action = 0.3 * torch.ones(3, 8, dtype=torch.float64)
    nxt, reward, _ = env.transition(dict(state.items()), action, params)
    forward = (nxt["torso_xy"][:, 0] - state["torso_xy"][:, 0]) / 0.05
    healthy = ((nxt["qpos"][:, 2] >= 0.2) & (nxt["qpos"][:, 2] <= 1.0)).double()
    expected = forward + healthy - 0.5 * (action**2).sum(-1) - 5e-4 * (nxt["cfrc_ext"].clamp(-1, 1) ** 2).sum((1, 2))
    torch.testing.assert_close(reward, expected)
    assert (nxt["cfrc_ext"].abs() > 1).any()  # the clip is exercised


def test_ant_healthy_range_is_closed():
    """Gymnasium's Ant checks ``min_z <= z <= max_z`` (the planar runners use open intervals)."""
    env = make_env("Ant-v5", num_envs=3, dtype=torch.float64, seed=0, params={"healthy_z_low": 0.0,
                                                                              "healthy_z_high": 100.0})
    state = env.initial_state(env.params, 3)
    state["qvel"] = torch.zeros_like(state["qvel"])
    qpos = state["qpos"].clone()
    qpos[:, 2] = 5.0
    state["qpos"] = qpos
    action = torch.zeros(3, 8, dtype=torch.float64)
    nxt, _, _ = env.transition(state, action, env.params)
    z = nxt["qpos"][:, 2]
    params = env.params.clone()
    params["healthy_z_low"] = torch.stack([z[0], z[1] + 1e-9, z[2] - 1e-9])
    params["healthy_z_high"] = torch.stack([z[0] + 1.0, z[1] + 1.0, z[2]])
    _, _, terminated = env.transition(state, action, params)
    assert terminated.tolist() == [False, True, False]
