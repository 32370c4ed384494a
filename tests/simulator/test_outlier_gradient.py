"""``gradient_outlier_clip``: a backward-only cap on the envs whose gradient explodes. The forward
values stay MuJoCo's, bit for bit; in the backward each env's cotangent of a step's physics
inputs is capped at a multiple of the batch's median (hand-computed below, and against the
unclipped autograd gradient of the same step); NaN/inf envs are zeroed; a large factor is the
unclipped gradient."""
from __future__ import annotations

import pytest
import torch

from torchrl_diffenvs.envs import make_env
from torchrl_diffenvs.envs.mujoco.outlier_gradient import clip_outlier_gradients
from torchrl_diffenvs.evaluation import gymnasium_kwargs


def test_cap_by_hand_one_outlier_a_nan_env_and_envs_without_gradient():
    a = torch.ones(6, 2, requires_grad=True)
    b = torch.ones(6, 1, requires_grad=True)
    ya, yb = clip_outlier_gradients(3.0, a, b)
    assert torch.equal(ya, a) and torch.equal(yb, b)
    # per-env cotangents: envs 0-2 of norm sqrt(3) (a: [1, 1], b: [1]); env 3 x100; env 4 NaN; env 5 zero
    weight = torch.tensor([1.0, 1.0, 1.0, 100.0, float("nan"), 0.0]).unsqueeze(-1)
    ((ya * weight).sum() + (yb * weight).sum()).backward()
    # median over the finite, nonzero envs (0-3): sqrt(3); env 3's norm 100 sqrt(3) is capped at 3 sqrt(3)
    expected = torch.tensor([1.0, 1.0, 1.0, 3.0, 0.0, 0.0]).unsqueeze(-1)
    torch.testing.assert_close(a.grad, expected.expand(6, 2), rtol=1e-6, atol=0)
    torch.testing.assert_close(b.grad, expected, rtol=1e-6, atol=0)


def test_no_env_with_a_gradient_one_env_and_off_leave_the_backward_alone():
    x = torch.ones(3, 2, requires_grad=True)
    (y,) = clip_outlier_gradients(2.0, x)
    (y * 0).sum().backward()
    assert torch.equal(x.grad, torch.zeros(3, 2))
    x.grad = None
    (y,) = clip_outlier_gradients(1.0, x)
    (y * torch.tensor([[0.0], [7.0], [0.0]])).sum().backward()  # one env with a gradient: its own median
    assert torch.equal(x.grad, torch.tensor([[0.0, 0.0], [7.0, 7.0], [0.0, 0.0]]))
    x.grad = None
    (y,) = clip_outlier_gradients(1.0, x)
    (y * torch.tensor([[0.0], [float("inf")], [0.0]])).sum().backward()  # a NaN/inf env is zeroed even then
    assert torch.equal(x.grad, torch.zeros(3, 2))
    assert clip_outlier_gradients(None, x)[0] is x  # off: the very tensors
    with torch.no_grad():
        assert clip_outlier_gradients(2.0, x)[0] is x


def test_a_float32_outlier_beyond_float32s_squares_is_capped_not_zeroed():
    x = torch.ones(4, 2, requires_grad=True)
    (y,) = clip_outlier_gradients(2.0, x)
    (y * torch.tensor([[1.0], [1.0], [1.0], [1e20]])).sum().backward()  # |g|^2 = 2e40: inf in float32
    torch.testing.assert_close(x.grad[:, 0], torch.tensor([1.0, 1.0, 1.0, 2.0]))


def test_a_second_derivative_through_the_cap_raises():
    x = torch.ones(3, 1, requires_grad=True)
    (y,) = clip_outlier_gradients(2.0, x)
    (g,) = torch.autograd.grad((y ** 3).sum(), x, create_graph=True)
    with pytest.raises(RuntimeError, match="once_differentiable|trying to differentiate twice"):
        g.sum().backward()


def _walker_step(clip, weight):
    """One Walker2d env step of 6 envs from fixed states in contact, through ``env.simulate``: the
    next state, and the gradient of ``sum_i weight_i * sum(next qvel_i)`` w.r.t. qpos, qvel and
    the action."""
    env = make_env("Walker2d-v5", num_envs=6, seed=0, dtype=torch.float64, gradient_outlier_clip=clip)
    td = env.reset()
    gen = torch.Generator().manual_seed(1)
    qpos = td["state", "qpos"].detach().clone()
    qpos[:, 1] -= 0.02  # feet pressed into the floor: the solve is active
    qvel = td["state", "qvel"].detach() + torch.randn(qpos.shape[0], env.model.nv, generator=gen, dtype=torch.float64)
    action = torch.rand(6, env.action_dim, generator=gen, dtype=torch.float64) * 2 - 1
    inputs = [t.clone().requires_grad_(True) for t in (qpos, qvel, action)]
    state = {"qpos": inputs[0], "qvel": inputs[1]}
    result = env.simulate(state, inputs[2], env.params)
    loss = (weight.unsqueeze(-1) * result.qvel).sum()
    return result, torch.autograd.grad(loss, inputs)


def test_env_step_keeps_its_values_and_caps_the_outlier_env_against_the_unclipped_gradient():
    weight = torch.tensor([1.0, 1.0, 1.0, 1.0, 1.0, 1e6], dtype=torch.float64)
    plain, plain_grads = _walker_step(None, weight)
    clipped, clipped_grads = _walker_step(4.0, weight)
    assert torch.equal(plain.qpos, clipped.qpos) and torch.equal(plain.qvel, clipped.qvel)
    norm = torch.stack([g.square().sum(-1) for g in plain_grads]).sum(0).sqrt()  # [6], joint over the inputs
    cap = 4.0 * norm.median()  # 6 envs: torch's median is the lower middle value, as nanmedian's
    assert norm[5] > cap and (norm[:5] <= cap).all()
    for plain_g, clipped_g in zip(plain_grads, clipped_grads):
        torch.testing.assert_close(clipped_g[:5], plain_g[:5], rtol=1e-12, atol=0)
        torch.testing.assert_close(clipped_g[5], plain_g[5] * cap / norm[5], rtol=1e-10, atol=0)
    # a factor beyond every env's ratio is the unclipped gradient
    _, loose = _walker_step(1e12, weight)
    for plain_g, loose_g in zip(plain_grads, loose):
        assert torch.equal(plain_g, loose_g)


def _hopper_rollout(clip, recompute=False, steps=10):
    """``steps`` Hopper env steps (3 envs, float64) under fixed actions: rewards, last observation,
    the gradient of the return w.r.t. the actions, and the last step's physics inputs."""
    env = make_env("Hopper-v5", num_envs=3, seed=2, dtype=torch.float64, gradient_outlier_clip=clip,
                   recompute_in_backward=recompute)
    actions = torch.rand(steps, 3, env.action_dim, dtype=torch.float64,
                         generator=torch.Generator().manual_seed(0)).mul(2).sub(1).requires_grad_(True)
    td, rewards = env.reset(), []
    for a in actions:
        td["action"] = a
        last = (td["state", "qpos"], td["state", "qvel"])
        td = env.step(td)
        rewards.append(td["next", "reward"])
        td = env.step_mdp(td)
    rewards = torch.stack(rewards)
    return rewards, td["observation"].detach(), actions, last, env


def test_rollout_keeps_its_values_and_the_last_step_is_capped_as_by_hand():
    plain_r, plain_obs, plain_a, plain_last, env = _hopper_rollout(None)
    clip_r, clip_obs, clip_a, _, _ = _hopper_rollout(1.0)
    assert torch.equal(plain_r, clip_r) and torch.equal(plain_obs, clip_obs)
    # the last action's gradient through the physics passes one cap: its cotangent there is the
    # last reward's gradient w.r.t. the physics inputs (qpos, qvel, action), by autograd without the cap
    plain_inputs = (*plain_last, plain_a)
    through_physics = list(torch.autograd.grad(plain_r[-1].sum(), plain_inputs, retain_graph=True))
    # outside the physics the reward reads the step's start x (x velocity: -w / dt there) and the
    # action (control cost: -2 c a); what is left went through the physics, and through the cap
    ctrl = -2 * env.params["ctrl_cost_weight"].unsqueeze(-1) * plain_a[-1].detach()
    through_physics[0] = through_physics[0].clone()
    through_physics[0][:, 0] += env.params["forward_reward_weight"] / env.dt
    action_physics = through_physics[2][-1] - ctrl
    norm = torch.stack([through_physics[0].square().sum(-1), through_physics[1].square().sum(-1),
                        action_physics.square().sum(-1)]).sum(0).sqrt()
    cap = norm.median()  # factor 1, three envs: the middle one
    assert (norm > cap).sum() == 1
    (clip_last_action,) = torch.autograd.grad(clip_r[-1].sum(), clip_a)
    expected = ctrl + action_physics * torch.clamp(cap / norm, max=1.0).unsqueeze(-1)
    torch.testing.assert_close(clip_last_action[-1], expected, rtol=1e-10, atol=1e-12)
    assert not torch.allclose(clip_last_action[-1], through_physics[2][-1], rtol=1e-6, atol=0)


def test_with_recompute_in_backward_the_same_values_and_gradients():
    rewards, obs, actions, _, _ = _hopper_rollout(1.5, steps=5)
    rewards_r, obs_r, actions_r, _, _ = _hopper_rollout(1.5, recompute=True, steps=5)
    assert torch.equal(rewards, rewards_r) and torch.equal(obs, obs_r)
    (grad,) = torch.autograd.grad(rewards.sum(), actions)
    (grad_r,) = torch.autograd.grad(rewards_r.sum(), actions_r)
    torch.testing.assert_close(grad, grad_r, rtol=1e-12, atol=1e-12)
    assert grad.abs().sum() > 0


@pytest.mark.parametrize("bad", [0.5, -1.0, float("inf"), True, "10"])
def test_a_bad_factor_names_what_is_valid(bad):
    with pytest.raises(ValueError, match="gradient_outlier_clip must be None .off. or a finite number >= 1"):
        make_env("Hopper-v5", num_envs=2, gradient_outlier_clip=bad)


def test_gymnasiums_env_is_made_without_it():
    kwargs = gymnasium_kwargs("Walker2d-v5", {"gradient_outlier_clip": 10.0, "recompute_in_backward": True,
                                              "forward_reward_weight": 2.0})
    assert kwargs == {"forward_reward_weight": 2.0}
