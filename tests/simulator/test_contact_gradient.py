"""The contact gradient modes (``contact_gradient``): every mode leaves MuJoCo's forward values
unchanged, bit for bit; CFD gives a foot just above the floor a gradient that the exact solve
cannot (zero beyond its distance); the smoothed active set tends to the exact gradient as its
softness goes to 0; the penalty mode's gradient is the smooth contact model's at MuJoCo's state."""
from __future__ import annotations

import pytest
import torch

from torchrl_diffenvs.articulated import step
from torchrl_diffenvs.articulated.collision import collide
from torchrl_diffenvs.articulated.contact_gradient import ContactGradient
from torchrl_diffenvs.articulated.kinematics import forward_kinematics
from torchrl_diffenvs.articulated.pipeline import accelerations, invweight0
from torchrl_diffenvs.envs import make_env


def _rollout(task, mode, steps=12, seed=3):
    """``steps`` env steps from a reset under fixed random actions: the observations and rewards,
    and the gradient of their sum with respect to the actions."""
    env = make_env(task, num_envs=2, seed=seed, dtype=torch.float64, contact_gradient=mode)
    actions = torch.rand(steps, 2, env.action_dim, dtype=torch.float64,
                         generator=torch.Generator().manual_seed(seed)) * 2 - 1
    actions.requires_grad_(True)
    td = env.reset()
    observations, rewards = [], []
    for a in actions:
        td["action"] = a
        td = env.step(td)
        observations.append(td["next", "observation"])
        rewards.append(td["next", "reward"])
        td = env.step_mdp(td)
    obs, rew = torch.stack(observations), torch.stack(rewards)
    (grad,) = torch.autograd.grad(rew.sum() + obs.sum(), actions)
    return obs.detach(), rew.detach(), grad


@pytest.mark.parametrize("task", ["Hopper-v5", "HalfCheetah-v5"])
def test_every_mode_keeps_mujocos_forward_values(task):
    steps = 8 if task == "Hopper-v5" else 12  # the Hopper (4 RK4 stages a physics step) lands in its 7th env step
    exact_obs, exact_rew, exact_grad = _rollout(task, "exact", steps)
    for mode in ("cfd", "smooth", "penalty"):
        obs, rew, grad = _rollout(task, mode, steps)
        assert torch.equal(obs, exact_obs) and torch.equal(rew, exact_rew), mode
        assert torch.isfinite(grad).all()
        assert not torch.equal(grad, exact_grad), f"{mode}: the gradient should differ once feet touch"


def _hopper_foot_above_floor(height: float):
    """The Hopper upright, falling at 0.5 m/s, its lowest point ``height`` above the floor."""
    env = make_env("Hopper-v5", num_envs=1, dtype=torch.float64)
    tree = env.tree
    qpos = tree.qpos0.unsqueeze(0).clone()
    dist = collide(tree.contact_slots, forward_kinematics(tree, qpos)).dist
    floor = tree.contact_slots.body[:, 0] == 0  # slots against the world's plane
    qpos[0, 1] -= dist[0, floor].min() - height
    qvel = torch.zeros(1, tree.nv, dtype=torch.float64)
    qvel[0, 1] = -0.5
    return env, qpos, qvel


def _height_gradient(mode, height: float) -> float:
    """``d qvel'_z / d qpos_z`` of one physics step (no contact exists at these heights)."""
    env, qpos, qvel = _hopper_foot_above_floor(height)
    tree = env.tree.use_contact_gradient(mode)
    params = dict(env.params.items())
    qpos.requires_grad_(True)
    ctrl = torch.zeros(1, tree.model.nu, dtype=torch.float64)
    result = step(tree, qpos, qvel, ctrl, params, tree.model.timestep, "euler", invweight0(tree, params))
    (grad,) = torch.autograd.grad(result.qvel[0, 1], qpos)
    return grad[0, 1].item()


def test_cfd_gives_a_gradient_just_above_the_floor_and_none_beyond_its_distance():
    margin = 0.002  # the Hopper's contact margin (geom margins summed)
    near = margin + 0.005
    assert _height_gradient("exact", near) == 0.0  # free fall: the exact gradient cannot see the floor
    cfd = _height_gradient(ContactGradient("cfd", distance=0.02), near)
    assert cfd < 0, "lower is pushed up harder: d qvel_z / d z must be negative"
    assert _height_gradient(ContactGradient("cfd", distance=0.02), margin + 0.03) == 0.0  # beyond the distance
    # a larger distance reaches it
    assert _height_gradient(ContactGradient("cfd", distance=0.05), margin + 0.03) < 0


def test_smooth_mode_tends_to_the_exact_gradient():
    _, _, exact = _rollout("HalfCheetah-v5", "exact", steps=10)
    _, _, soft = _rollout("HalfCheetah-v5", ContactGradient("smooth", softness=1e-14), steps=10)
    torch.testing.assert_close(soft, exact, rtol=1e-7, atol=1e-9)
    _, _, smooth = _rollout("HalfCheetah-v5", ContactGradient("smooth", softness=0.3), steps=10)
    assert (smooth - exact).norm() > 1e-6 * exact.norm()


@pytest.mark.parametrize("task,implicit", [("Hopper-v5", False), ("Ant-v5", False), ("Hopper-v5", True)])
def test_penalty_mode_differentiates_the_smooth_contact_model_at_mujocos_state(task, implicit):
    """Value: MuJoCo's ``qacc``; gradient: the smooth model's, its contact damping implicit at the
    physics step (the two trees are built independently, one per contact model). ``implicit``:
    MuJoCo's implicit integrator's acceleration (the bias forces' velocity Jacobian, which the two
    forwards share, in the solve)."""
    penalty = make_env(task, num_envs=2, seed=1, dtype=torch.float64, contact_gradient="penalty")
    smooth = make_env(task, num_envs=2, seed=1, dtype=torch.float64, contact="smooth")
    exact = make_env(task, num_envs=2, seed=1, dtype=torch.float64)
    for name in ("contact_stiffness", "contact_damping", "contact_width", "friction_velocity"):
        assert torch.equal(penalty.params[name], smooth.params[name]), name
    tree = penalty.tree
    qpos = tree.qpos0.expand(2, -1).clone()
    height = 2 if task == "Ant-v5" else 1  # the root's z in qpos
    lowest = collide(tree.contact_slots, forward_kinematics(tree, qpos)).dist.min(-1).values
    qpos[:, height] -= lowest + torch.tensor([0.003, 0.0005], dtype=torch.float64)  # 3 mm and 0.5 mm into the floor
    qvel = torch.randn(2, tree.nv, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 0.3
    ctrl = torch.full((2, tree.model.nu), 0.2, dtype=torch.float64)

    def qacc_and_jacobian(env, **kw):
        params = dict(env.params.items())
        q, v = qpos.clone().requires_grad_(True), qvel.clone().requires_grad_(True)
        qacc = accelerations(env.tree, q, v, ctrl, params, invweight0=invweight0(env.tree, params), **kw)
        rows = [torch.cat(torch.autograd.grad(qacc[:, i].sum(), (q, v), retain_graph=True), -1)
                for i in range(tree.nv)]
        return qacc.detach(), torch.stack(rows, 1)

    integrator = dict(implicit_damping_dt=tree.model.timestep, implicit_bias=True) if implicit else {}
    value, jacobian = qacc_and_jacobian(penalty, **integrator)
    exact_value, exact_jacobian = qacc_and_jacobian(exact, **integrator)
    smooth_value, smooth_jacobian = qacc_and_jacobian(smooth, **{"implicit_damping_dt": tree.model.timestep,
                                                                 **integrator})
    assert torch.equal(value, exact_value)
    torch.testing.assert_close(jacobian, smooth_jacobian, rtol=1e-10, atol=1e-8)
    assert (smooth_value - exact_value).abs().max() > 1e-3  # the two models' values differ: not a tautology
    assert (jacobian - exact_jacobian).abs().max() > 1e-3


@pytest.mark.parametrize("mode", ["exact", "cfd", "smooth"])
def test_the_surrogate_is_the_same_without_row_compaction(mode, monkeypatch):
    """On the CPU the constraint stage leaves out the contact slots and the solve the rows that no
    env needs; on a GPU and under torch.compile they keep them all: values and gradients (and the
    contact wrenches) must not depend on it. The upright Hopper's capsules are parallel (a
    degenerate branch of the collision, whose gradient must stay finite)."""
    env, qpos, qvel = _hopper_foot_above_floor(-0.003)  # 3 mm into the floor: contacts and near contacts
    qpos, qvel = qpos.expand(2, -1).clone(), qvel.expand(2, -1).clone()
    qpos[1, 1] += 0.01  # the second env 7 mm above it
    tree = env.tree.use_contact_gradient(mode)
    params = {k: v.expand(2, *v.shape[1:]) for k, v in env.params.items()}
    ctrl = torch.full((2, tree.model.nu), 0.3, dtype=torch.float64)
    out, used = [], []
    from torchrl_diffenvs.articulated import convergence, pipeline

    slots_in_use = pipeline._slots_in_use
    monkeypatch.setattr(pipeline, "_slots_in_use", lambda *a: (lambda r: used.append(r[0].count) or r)(slots_in_use(*a)))
    for reads_data in (True, False):  # the CPU's compacted problem, then every slot, row and env (a GPU's)
        monkeypatch.setattr(convergence, "reads_data_freely", lambda device, reads_data=reads_data: reads_data)
        q = qpos.clone().requires_grad_(True)
        result = step(tree, q, qvel, ctrl, params, tree.model.timestep, "euler", invweight0(tree, params))
        wrench = pipeline.body_contact_wrenches(tree, q, qvel, ctrl, params, about=q.new_zeros(2, 3))
        (grad,) = torch.autograd.grad(result.qvel.sum() + wrench.sum(), q)
        out.append((result.qvel.detach(), wrench.detach(), grad))
    assert 0 < used[0] < tree.contact_slots.count  # the slots touching nothing were left out
    for compacted, every_row, tolerance in zip(out[0], out[1], (1e-12, 1e-12, 1e-9)):
        torch.testing.assert_close(compacted, every_row, rtol=tolerance, atol=tolerance)
    assert out[0][1].abs().sum() > 0 and out[0][2].abs().sum() > 0


def test_contact_gradient_option_errors_name_what_is_valid():
    with pytest.raises(ValueError, match="unknown mode 'soft'.*'exact', 'cfd', 'smooth', 'penalty'"):
        make_env("Hopper-v5", contact_gradient="soft")
    with pytest.raises(ValueError, match="unknown keys \\['width'\\]"):
        make_env("Hopper-v5", contact_gradient={"mode": "cfd", "width": 0.1})
    with pytest.raises(ValueError, match="distance must be a number > 0"):
        make_env("Hopper-v5", contact_gradient={"mode": "cfd", "distance": -1})
    with pytest.raises(ValueError, match="a mapping must name its mode"):
        make_env("Hopper-v5", contact_gradient={"distance": 0.05})
    with pytest.raises(ValueError, match="'smooth' contact model"):
        make_env("Hopper-v5", contact="smooth", contact_gradient="cfd")
    with pytest.raises(ValueError, match="'smooth' contact model"):
        make_env("Hopper-v5", contact="smooth", contact_gradient="penalty")
    assert make_env("Hopper-v5", contact_gradient={"mode": "cfd", "distance": 0.05}).contact_gradient.distance == 0.05
