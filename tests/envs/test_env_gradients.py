"""Gradients of every env against independent references (float64).

* one step: ``torch.autograd.gradcheck`` (autograd vs finite differences) w.r.t. the action,
  every state entry and every physical parameter;
* a 20-step rollout through ``env.rollout``: the autograd gradient of the summed signal w.r.t.
  every action, every initial-state entry (``env.reset(td, set_state=True)``) and every
  physical parameter equals central finite differences;
* the auto-reset cuts the gradient: nothing after a reset depends on actions before it;
* gradients reach a policy's parameters through ``env.rollout(T, policy)`` (the issue's example).

The test signal is ``reward + w . next_observation`` (see ``_env_helpers.obs_weights``): for the
Ivy tasks it is dominated by the reward, and it keeps the checks meaningful for CartPole-v1,
whose reward is a constant. Gymnasium variants are checked away from their clips and
thresholds (actions at half the spec range, short horizons), where they are smooth.
"""
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from _env_helpers import classic_envs, F64, ReplayPolicy, in_spec_actions, make, obs_weights, signal, start_td, use_rollout_path

ALL_ENVS = classic_envs()
EPS = 1e-6  # central differences in float64: truncation ~1e-12, round-off ~1e-10


def _keys(td: TensorDict) -> list[str]:
    return sorted(td.keys())


# ---------------------------------------------------------------------------- one step
@pytest.mark.parametrize("name", ALL_ENVS)
def test_one_step_gradcheck(name):
    """d(next obs, reward, next state) / d(action, state, params) of one env.step is correct."""
    env = make(name, 2)
    td0 = env.reset()
    state_keys, param_keys = _keys(td0["state"]), _keys(td0["params"])
    action = in_spec_actions(env, 2).requires_grad_()
    state = [td0["state", k].clone().requires_grad_() for k in state_keys]
    params = [td0["params", k].clone().requires_grad_() for k in param_keys]

    def one_step(action, *tensors):
        td = TensorDict(
            {
                "action": action,
                "state": dict(zip(state_keys, tensors[: len(state_keys)])),
                "params": dict(zip(param_keys, tensors[len(state_keys):])),
                "episode_step": td0["episode_step"],
            },
            batch_size=[2],
        )
        nxt = env.step(td)["next"]
        outs = (nxt["observation"], nxt["reward"], *(nxt["state", k] for k in state_keys))
        # gradcheck silently skips outputs that do not require grad: a reward detached by
        # mistake would pass. Adding 0 * action makes every output differentiable (its
        # analytical Jacobian is then 0 and must match the numerical one).
        anchor = 0.0 * action.sum()
        return tuple(o + anchor for o in outs)

    assert torch.autograd.gradcheck(one_step, (action, *state, *params), eps=EPS, atol=1e-7, rtol=1e-5)
    # the check is only meaningful if the step depends on each input group
    outs = one_step(action, *state, *params)
    grads = torch.autograd.grad(sum(o.sum() for o in outs), (action, *state), allow_unused=True)
    assert all(g is not None and g.abs().sum() > 0 for g in grads), "an input has no effect on the step"


# ---------------------------------------------------------------------------- 20-step rollouts
T_FD = 20


def _flat(d: dict[str, torch.Tensor], n: int) -> torch.Tensor:
    return torch.cat([d[k].reshape(n, -1) for k in sorted(d)], dim=-1)


def _unflat(x: torch.Tensor, like: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    out, i = {}, 0
    for k in sorted(like):
        shape = like[k].shape[1:]
        size = shape.numel()
        out[k] = x[:, i : i + size].reshape(x.shape[0], *shape)
        i += size
    return out


def _rollout_objective(name, state, params, actions, w, fast):
    """Summed signal ``[B]`` of a T-step ``env.rollout`` from ``state`` with per-env ``params``."""
    n = actions.shape[0]
    env = make(name, n, max_episode_steps=None)
    use_rollout_path(env, fast)  # DiffEnv's lean loop, or TorchRL's EnvBase.rollout
    td = start_td(env, state, params)
    traj = env.rollout(
        actions.shape[1], ReplayPolicy(actions), tensordict=td, auto_reset=False, break_when_any_done=False
    )
    # the finite-difference reference needs a smooth path: no termination on the way
    assert not traj["next", "done"].any(), f"{name}: an episode ended inside the gradient check"
    return signal(traj, w).sum(-1)


@pytest.mark.parametrize("fast", [True, False], ids=["fast_rollout", "EnvBase.rollout"])
@pytest.mark.parametrize("wrt", ["action", "state", "params"])
@pytest.mark.parametrize("name", ALL_ENVS)
def test_rollout_gradient_matches_finite_differences(name, wrt, fast):
    """Autograd through a 20-step env.rollout equals central differences, for every input entry.

    All perturbed copies run as one batch (envs of a batch are independent: tested in
    test_env_behaviour.py), so the reference costs one rollout.
    """
    n = 2
    env = make(name, n)
    td0 = env.reset()
    inputs = {
        "action": {"a": in_spec_actions(env, n, T_FD)},
        "state": {k: v.detach() for k, v in td0["state"].items()},
        "params": {k: v.detach() for k, v in td0["params"].items()},
    }
    w = obs_weights(env)

    def objective(groups):
        return _rollout_objective(name, groups["state"], groups["params"], groups["action"]["a"], w, fast)

    x = _flat(inputs[wrt], n).clone().requires_grad_()
    grads = torch.autograd.grad(objective({**inputs, wrt: _unflat(x, inputs[wrt])}).sum(), x)[0]

    # reference: for every coordinate j, +eps and -eps copies of the n envs -> 2 * D * n envs
    d = x.shape[1]
    bump = EPS * torch.eye(d, dtype=F64)
    xs = torch.stack([x.detach() + bump[:, None], x.detach() - bump[:, None]])  # [2, D, n, D]
    big = {g: {k: v.repeat(2 * d, *([1] * (v.ndim - 1))) for k, v in inputs[g].items()} for g in inputs}
    big[wrt] = _unflat(xs.reshape(2 * d * n, d), inputs[wrt])
    f = objective(big).reshape(2, d, n)
    fd = ((f[0] - f[1]) / (2 * EPS)).T  # [n, D]

    assert grads.abs().max() > 1e-6, f"{name}: the signal does not depend on the {wrt}"
    torch.testing.assert_close(grads, fd, rtol=1e-5, atol=1e-7)


# ---------------------------------------------------------------------------- auto-reset
def _episode_ids(done: torch.Tensor) -> torch.Tensor:
    """``[N, T]`` episode index of each step, given ``("next", "done")`` ``[N, T]``."""
    return torch.cat([torch.zeros_like(done[:, :1], dtype=torch.long), done[:, :-1].long().cumsum(1)], dim=1)


def _check_reset_cuts_gradient(sig, actions, done):
    """d sig[:, t] / d actions[:, s] is exactly zero across a reset and nonzero within an episode."""
    episode = _episode_ids(done)
    n, t_max = sig.shape
    for t in range(t_max):
        grad = torch.autograd.grad(sig[:, t].sum(), actions, retain_graph=True, allow_unused=True)[0]
        grad = torch.zeros_like(actions) if grad is None else grad
        per_step = grad.abs().sum(-1)  # [N, T]: envs are independent, so this is per env
        for i in range(n):
            for s in range(t_max):
                if s > t:
                    assert per_step[i, s] == 0, "a reward depends on a future action"
                elif episode[i, s] != episode[i, t]:
                    assert per_step[i, s] == 0, f"env {i}: step {t} depends on action {s} across a reset"
                else:
                    assert per_step[i, s] > 0, f"env {i}: step {t} lost its gradient to action {s}"


@pytest.mark.parametrize("name", ALL_ENVS)
def test_gradient_is_cut_at_auto_reset_step_and_maybe_reset(name):
    """A manual loop of env.step_and_maybe_reset: the reset starts a fresh graph."""
    env = make(name, 2, max_episode_steps=3)
    actions = in_spec_actions(env, 2, 7).requires_grad_()
    w = obs_weights(env)
    td, out = env.reset(), []
    for t in range(actions.shape[1]):
        td["action"] = actions[:, t]
        step, td = env.step_and_maybe_reset(td)
        out.append(step)
    traj = torch.stack(out, dim=1)
    done = traj["next", "done"][..., 0]
    assert done[:, 2].all() and done[:, 5].all(), "episodes of 3 steps expected"
    _check_reset_cuts_gradient(signal(traj, w), actions, done)


@pytest.mark.parametrize("name", ALL_ENVS)
def test_gradient_is_cut_at_auto_reset_rollout(name):
    """env.rollout(break_when_any_done=False) with short episodes: same exact-zero rule."""
    env = make(name, 2, max_episode_steps=3)
    actions = in_spec_actions(env, 2, 7).requires_grad_()
    traj = env.rollout(7, ReplayPolicy(actions), break_when_any_done=False)
    done = traj["next", "done"][..., 0]
    assert done[:, 2].all() and done[:, 5].all(), "episodes of 3 steps expected"
    _check_reset_cuts_gradient(signal(traj, obs_weights(env)), actions, done)


# ---------------------------------------------------------------------------- policies
class _TanhPolicy(torch.nn.Module):
    def __init__(self, obs_dim, act_dim, dtype):
        super().__init__()
        self.net = torch.nn.Sequential(
            torch.nn.Linear(obs_dim, 16, dtype=dtype), torch.nn.Tanh(), torch.nn.Linear(16, act_dim, dtype=dtype)
        )

    def forward(self, obs):
        return torch.tanh(self.net(obs))


def test_gradients_reach_policy_parameters_swimmer_64():
    """The issue's example: swimmer, 64 envs, float32; every policy parameter gets a gradient."""
    torch.manual_seed(0)
    env = make("swimmer", 64, dtype=torch.float32)
    policy = TensorDictModule(_TanhPolicy(env.observation_dim, env.action_dim, torch.float32),
                              in_keys=["observation"], out_keys=["action"])
    td = env.rollout(100, policy)
    assert td.batch_size == (64, 100)
    (-td["next", "reward"].sum(-2).mean()).backward()
    for name, p in policy.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name


def test_policy_gradient_matches_finite_differences():
    """d(summed reward)/d(policy weights) through env.rollout equals central differences."""
    torch.manual_seed(0)
    env = make("swimmer", 8, seed=3)
    policy = TensorDictModule(_TanhPolicy(env.observation_dim, env.action_dim, F64),
                              in_keys=["observation"], out_keys=["action"])
    start = env.reset()

    def objective():
        td = env.rollout(20, policy, tensordict=start.clone(), auto_reset=False)
        return td["next", "reward"].sum()

    weight = policy.module.net[0].weight
    (grad,) = torch.autograd.grad(objective(), weight)
    with torch.no_grad():
        for idx in [(0, 0), (3, 5), (15, 15)]:
            orig = weight[idx].item()
            weight[idx] = orig + EPS
            plus = objective()
            weight[idx] = orig - EPS
            minus = objective()
            weight[idx] = orig
            torch.testing.assert_close(grad[idx], (plus - minus) / (2 * EPS), rtol=1e-5, atol=1e-8)
