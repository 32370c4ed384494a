"""AHAC and SAPO: the horizon rule, the temperature update, the twin-critic reductions and the
soft critic targets against hand-computed values; the squashed-normal log-probability against
TorchRL's ``TanhNormal``; the learners on small envs and through ``sota_scripts/train.py``."""
from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from tensordict import TensorDict
from torch import nn
from torchrl.data import Unbounded
from torchrl.envs import Transform, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import TanhNormal

from torchrl_diffenvs import make_env
from torchrl_diffenvs.learners import LEARNERS, AHACConfig, AHACLearner, SAPOConfig, SAPOLearner, make_learner
from torchrl_diffenvs.modules import LeanModule, make_actor, make_critic, make_sapo_actor
from torchrl_diffenvs.objectives import AHACLoss, AdaptiveHorizon, SAPOLoss, TwinCritic
from _env_helpers import with_smooth_contact  # noqa: E402

# written for the smooth contact option (MuJoCo's own: tests/simulator/test_mujoco_contact.py)
make_env = with_smooth_contact(make_env)

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"


# ---------------------------------------------------------------------- helpers
class StubContactForce(Transform):
    """Writes ``"contact_force"`` ``[N, 1]`` at every step, detached: ``constant`` if given,
    else ``scale`` times the largest absolute observation entry (a stand-in for the MuJoCo
    tasks' largest contact normal force)."""

    def __init__(self, constant: float | None = None, scale: float = 100.0):
        super().__init__(in_keys=["observation"], out_keys=["contact_force"])
        self.constant, self.scale = constant, scale

    def _call(self, tensordict):
        obs = tensordict.get("observation").detach()
        if self.constant is not None:
            force = torch.full((*obs.shape[:-1], 1), self.constant, dtype=obs.dtype, device=obs.device)
        else:
            force = self.scale * obs.abs().amax(-1, keepdim=True)
        tensordict.set("contact_force", force)
        return tensordict

    def _reset(self, tensordict, tensordict_reset):
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec):
        observation_spec["contact_force"] = Unbounded(shape=(*observation_spec.shape, 1),
                                                      dtype=observation_spec["observation"].dtype,
                                                      device=observation_spec.device)
        return observation_spec


class ContactForceFromState(Transform):
    """Writes ``"contact_force"`` ``[N, 1]`` for a MuJoCo contact task: the largest contact normal
    force of its smooth contact model at the step's final state (what the tasks will write
    themselves), detached."""

    def __init__(self, env):
        super().__init__(in_keys=[("state", "qpos")], out_keys=["contact_force"])
        self.tree = env.tree

    def _call(self, tensordict):
        from torchrl_diffenvs.articulated.contact import _contact_points_and_forces
        from torchrl_diffenvs.articulated.dynamics import forward_kinematics

        with torch.no_grad():
            qpos, qvel = tensordict.get(("state", "qpos")), tensordict.get(("state", "qvel"))
            contacts = _contact_points_and_forces(self.tree, forward_kinematics(self.tree, qpos), qvel,
                                                  tensordict.get("params"))
            tensordict.set("contact_force", contacts.normal_force.amax(-1, keepdim=True))
        return tensordict

    def _reset(self, tensordict, tensordict_reset):
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec):
        observation_spec["contact_force"] = Unbounded(shape=(*observation_spec.shape, 1),
                                                      dtype=observation_spec["observation"].dtype,
                                                      device=observation_spec.device)
        return observation_spec


def constant_critic(value: float, dtype=torch.float64) -> LeanModule:
    """A critic whose value is ``value`` everywhere (weights 0, bias ``value``)."""
    layer = nn.Linear(3, 1, dtype=dtype)
    with torch.no_grad():
        layer.weight.zero_()
        layer.bias.fill_(value)
    return LeanModule(layer, in_keys=["observation"], out_keys=["state_value"])


def two_step_window(reward, log_prob=None, done_first=False, terminated_first=False) -> TensorDict:
    """A window ``[1, 2]`` (one env, two steps) with the entries the losses read."""
    obs = torch.zeros(1, 2, 3, dtype=torch.float64)
    done = torch.tensor([[[done_first], [False]]])
    data = {
        "observation": obs,
        "next": {
            "observation": obs.clone(),
            "reward": torch.tensor(reward, dtype=torch.float64).reshape(1, 2, 1),
            "done": done,
            "terminated": torch.tensor([[[terminated_first], [False]]]),
        },
    }
    if log_prob is not None:
        data["action_log_prob"] = torch.tensor(log_prob, dtype=torch.float64).reshape(1, 2)
    return TensorDict(data, batch_size=[1, 2])


def pendulum_with_contact(num_envs=4, **stub):
    return TransformedEnv(make_env("pendulum", num_envs=num_envs, seed=0), StubContactForce(**stub))


def tiny_twin_critic(env, hidden=(16,)):
    return TwinCritic(make_critic(env, hidden=hidden), make_critic(env, hidden=hidden))


# ---------------------------------------------------------------------- AHAC's horizon rule
def test_adaptive_horizon_follows_the_reference_rule_by_hand():
    """lambda_i -= lr (C - mean_envs f_i); H += lr sum(lambda), clipped to [8, 64]; lambda <- [lambda_0] * round(H)."""
    rule = AdaptiveHorizon(min_horizon=8, max_horizon=64, contact_threshold=500.0)
    assert rule.steps == 8 and rule.horizon == 8.0 and rule.dual.tolist() == [0.0] * 8
    # forces above C: lambda = 0 - 0.01 (500 - 600) = 1 per step; H = 8 + 0.01 * 8
    assert rule.update(torch.full((8,), 600.0), lr=0.01) == 8
    assert rule.horizon == pytest.approx(8.08) and rule.dual.tolist() == pytest.approx([1.0] * 8)
    # lambda = 1 + 0.01 * 1000 = 11; H = 8.08 + 0.01 * 88 = 8.96 -> 9 steps
    assert rule.update(torch.full((8,), 1500.0), lr=0.01) == 9
    assert rule.horizon == pytest.approx(8.96) and rule.dual.tolist() == pytest.approx([11.0] * 9)
    # no contact: lambda = 11 - 5 = 6; H = 8.96 + 0.54 = 9.5 -> round(9.5) = 10 (Python's rounding, as the reference)
    assert rule.update(torch.zeros(9), lr=0.01) == 10
    assert rule.horizon == pytest.approx(9.5) and rule.dual.tolist() == pytest.approx([6.0] * 10)
    # two envs [N, H]: the per-step mean over envs; step 0 mean 800 -> 9, others mean 200 -> 3;
    # H = 9.5 + 0.01 * (9 + 9 * 3) = 9.86; the next dual repeats lambda_0 = 9
    forces = torch.stack([torch.full((10,), 100.0), torch.full((10,), 300.0)])
    forces[:, 0] = torch.tensor([700.0, 900.0])
    assert rule.update(forces, lr=0.01) == 10
    assert rule.horizon == pytest.approx(9.86) and rule.dual.tolist() == pytest.approx([9.0] * 10)
    # lambda = 9 - 500 = -491 (not clipped at 0, as the reference); H clipped at min_horizon
    assert rule.update(torch.zeros(10), lr=1.0) == 8
    assert rule.horizon == 8.0 and rule.dual.tolist() == pytest.approx([-491.0] * 8)
    # and at max_horizon: lambda = -491 + 1e4 = 9509, H = 8 + 8 * 9509 -> 64
    assert rule.update(torch.full((8,), 10_500.0), lr=1.0) == 64 and rule.horizon == 64.0
    assert rule.dual.tolist() == pytest.approx([9509.0] * 64)
    with pytest.raises(ValueError, match="the window has 8 steps but the dual variable 64"):
        rule.update(torch.zeros(8), lr=0.01)


def test_adaptive_horizon_state_round_trips():
    rule = AdaptiveHorizon(contact_threshold=100.0)
    rule.update(torch.full((8,), 5000.0), lr=0.01)
    other = AdaptiveHorizon(contact_threshold=100.0)
    other.load_state_dict(rule.state_dict())
    assert other.horizon == rule.horizon and torch.equal(other.dual, rule.dual) and other.steps == rule.steps == 12


# ---------------------------------------------------------------------- the losses by hand
GAMMA, LMBDA = 0.9, 0.8


def test_ahac_bootstraps_the_actor_and_the_targets_with_the_twin_critics_minimum():
    critic = TwinCritic(constant_critic(3.0), constant_critic(5.0))
    loss = AHACLoss(nn.Linear(1, 1), critic, gamma=GAMMA, lmbda=LMBDA)
    window = two_step_window([1.0, 2.0])
    out = loss(window)
    v = 3.0  # min(3, 5)
    assert out["loss_actor"].item() == pytest.approx(-(1.0 + GAMMA * 2.0 + GAMMA**2 * v) / 2)
    g1 = 2.0 + GAMMA * v  # the window end closes the trajectory
    g0 = 1.0 + GAMMA * ((1 - LMBDA) * v + LMBDA * g1)
    assert window["value_target"].reshape(-1).tolist() == pytest.approx([g0, g1])
    # both critics fit the same targets: the mean of their squared errors
    flat = window.reshape(-1)
    expected = ((3.0 - g0) ** 2 + (5.0 - g0) ** 2 + (3.0 - g1) ** 2 + (5.0 - g1) ** 2) / 4
    assert loss.critic_loss(flat)["loss_critic"].item() == pytest.approx(expected)
    # no target critic: a changed critic changes the bootstrap at once
    with torch.no_grad():
        critic.second.module.bias.fill_(1.0)
    assert loss(two_step_window([1.0, 2.0]))["loss_actor"].item() == pytest.approx(-(1.0 + GAMMA * 2.0 + GAMMA**2) / 2)
    with pytest.raises(RuntimeError, match="no target critic"):
        loss.make_target_updater()


def test_ahac_terminal_state_is_worth_zero():
    loss = AHACLoss(nn.Linear(1, 1), TwinCritic(constant_critic(3.0), constant_critic(5.0)), gamma=GAMMA, lmbda=LMBDA)
    out = loss(two_step_window([1.0, 2.0], done_first=True, terminated_first=True))
    assert out["loss_actor"].item() == pytest.approx(-(1.0 + 2.0 + GAMMA * 3.0) / 2)


@pytest.mark.parametrize("normalised", [False, True])
def test_sapo_soft_targets_and_actor_loss_by_hand(normalised):
    critic = TwinCritic(constant_critic(3.0), constant_critic(5.0))
    loss = SAPOLoss(nn.Linear(1, 1), critic, action_dim=2, gamma=GAMMA, lmbda=LMBDA, init_alpha=0.5,
                    entropy_offset=normalised, entropy_scale=normalised)
    log_prob = [0.7, -1.3]
    window = two_step_window([1.0, 2.0], log_prob)
    out = loss(window)
    alpha, target = 0.5, -1.0  # -0.5 * |A|
    if normalised:
        bonus = [((-lp + 1.0) / 2) / 1.0 for lp in log_prob]
    else:
        bonus = [-lp for lp in log_prob]  # r_t - alpha * log_prob
    s0, s1 = 1.0 + alpha * bonus[0], 2.0 + alpha * bonus[1]
    # critic targets: soft rewards, minimum of the critics
    g1 = s1 + GAMMA * 3.0
    g0 = s0 + GAMMA * ((1 - LMBDA) * 3.0 + LMBDA * g1)
    assert window["value_target"].reshape(-1).tolist() == pytest.approx([g0, g1])
    # actor: soft rewards, mean of the critics
    assert out["loss_actor"].item() == pytest.approx(-(s0 + GAMMA * s1 + GAMMA**2 * 4.0) / 2)
    assert out["entropy"].item() == pytest.approx(-(0.7 - 1.3) / 2) and out["alpha"].item() == pytest.approx(0.5)
    assert loss.target_entropy == target
    # compute_value_targets uses the temperature as it is now
    with torch.no_grad():
        loss.log_alpha.fill_(math.log(2.0))
    fresh = two_step_window([1.0, 2.0], log_prob)
    loss.compute_value_targets(fresh)
    s0, s1 = 1.0 + 2.0 * bonus[0], 2.0 + 2.0 * bonus[1]
    g1 = s1 + GAMMA * 3.0
    assert fresh["value_target"].reshape(-1).tolist() == pytest.approx([s0 + GAMMA * (0.2 * 3.0 + 0.8 * g1), g1])


def test_sapo_actor_loss_carries_the_entropy_gradient():
    loss = SAPOLoss(nn.Linear(1, 1), TwinCritic(constant_critic(0.0), constant_critic(0.0)), action_dim=2,
                    gamma=GAMMA, lmbda=LMBDA, init_alpha=0.5, entropy_offset=False, entropy_scale=False)
    window = two_step_window([0.0, 0.0], [0.0, 0.0])
    log_prob = window["action_log_prob"].requires_grad_()
    loss(window)["loss_actor"].backward()
    # loss = -(alpha * -lp0 + gamma * alpha * -lp1) / 2
    assert log_prob.grad.reshape(-1).tolist() == pytest.approx([0.5 / 2, GAMMA * 0.5 / 2])


def test_sapo_losses_refuse_a_window_without_log_probabilities():
    loss = SAPOLoss(nn.Linear(1, 1), TwinCritic(constant_critic(0.0), constant_critic(0.0)), action_dim=1)
    with pytest.raises(KeyError, match="'action_log_prob' entry: the actor must write"):
        loss(two_step_window([0.0, 0.0]))


# ---------------------------------------------------------------------- SAPO's actor and temperature
def test_squashed_normal_log_prob_is_tanh_normals_and_stays_finite_when_saturated():
    env = make_env("Pendulum-v1", num_envs=64, seed=0, dtype=torch.float64)  # action bounds [-2, 2]
    actor = make_sapo_actor(env, hidden=(16,), min_log_std=-1.0, max_log_std=0.0)
    td = env.reset()
    torch.manual_seed(1)
    with set_exploration_type(ExplorationType.RANDOM):
        out = actor(td.clone())
    dist = TanhNormal(out["loc"], out["scale"], low=-2.0, high=2.0)
    torch.testing.assert_close(out["action_log_prob"], dist.log_prob(out["action"]), rtol=1e-7, atol=1e-7)
    assert out["scale"].min() >= math.exp(-1.0) - 1e-12 and out["scale"].max() <= 1.0 + 1e-12
    # the same random stream as Normal.rsample (as the project's other actors draw)
    torch.manual_seed(1)
    eps = torch.distributions.Normal(torch.zeros_like(out["loc"]), torch.ones_like(out["loc"])).rsample()
    torch.testing.assert_close(out["action"], 2.0 * torch.tanh(out["loc"] + eps * out["scale"]))
    # deterministic: the squashed mean, no sampling
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        mean = actor(td.clone())
    torch.testing.assert_close(mean["action"], 2.0 * torch.tanh(mean["loc"]))
    # float32, saturated (loc ~ 12: tanh rounds to 1): finite, and the exact log-probability from the pre-tanh sample
    env32 = make_env("Pendulum-v1", num_envs=4, seed=0)
    actor32 = make_sapo_actor(env32, hidden=(8,), min_log_std=-3.0, max_log_std=-3.0)
    with torch.no_grad():
        actor32.module[0].module[0][-1].bias[0] = 12.0
    torch.manual_seed(2)
    with set_exploration_type(ExplorationType.RANDOM):
        sat = actor32(env32.reset())
    assert torch.isfinite(sat["action_log_prob"]).all() and (sat["action"].abs() > 2.0 - 1e-5).all()
    torch.manual_seed(2)
    eps = torch.distributions.Normal(torch.zeros_like(sat["loc"]), torch.ones_like(sat["loc"])).rsample().double()
    loc, scale = sat["loc"].double(), sat["scale"].double()
    u = loc + eps * scale
    exact = (torch.distributions.Normal(loc, scale).log_prob(u) - torch.log(1 - torch.tanh(u) ** 2) - math.log(2.0)).sum(-1)
    torch.testing.assert_close(sat["action_log_prob"].double(), exact, rtol=1e-4, atol=1e-3)
    # TorchRL's TanhNormal.log_prob of the same float32 action is far off there (why the actor computes its own)
    off = TanhNormal(sat["loc"], sat["scale"], low=-2.0, high=2.0).log_prob(sat["action"]).double()
    assert (off - exact).abs().max() > 1.0


def test_sapo_temperature_update_by_hand():
    """alpha' = exp(log_alpha) |target|; loss = alpha' (H - target); AdamW (betas 0.7, 0.95, decay 0.01),
    gradient clipped at 0.5."""
    env = make_env("pendulum", num_envs=4, seed=0)  # |A| = 1: target entropy -0.5
    config = SAPOConfig(horizon=4, critic_passes=1)
    learner = SAPOLearner(env, make_sapo_actor(env, hidden=(8,)), tiny_twin_critic(env), config, 1000)
    lr, (b1, b2), wd, eps = 5e-3, (0.7, 0.95), 0.01, 1e-8
    assert learner.loss.log_alpha.item() == 0.0 and learner.loss.target_entropy == -0.5
    # step 1: H = 0.3 -> gradient 1 * 0.5 * (0.3 + 0.5) = 0.4 (below the clip)
    info = learner.update_temperature(0.3)
    assert info["grad_norm_alpha"] == pytest.approx(0.4) and info["loss_alpha"] == pytest.approx(0.4)
    g1 = 0.4
    m, v = (1 - b1) * g1, (1 - b2) * g1**2
    la = 0.0 * (1 - lr * wd) - lr * (m / (1 - b1)) / (math.sqrt(v / (1 - b2)) + eps)
    assert learner.loss.log_alpha.item() == pytest.approx(la, rel=1e-5)
    # step 2: H = -2 -> gradient exp(la) * 0.5 * (-1.5), clipped to norm 0.5
    raw = math.exp(la) * 0.5 * (-2.0 + 0.5)
    g2 = raw * 0.5 / (abs(raw) + 1e-6)
    info = learner.update_temperature(-2.0)
    assert info["grad_norm_alpha"] == pytest.approx(abs(raw), rel=1e-5)
    m, v = b1 * m + (1 - b1) * g2, b2 * v + (1 - b2) * g2**2
    la = la * (1 - lr * wd) - lr * (m / (1 - b1**2)) / (math.sqrt(v / (1 - b2**2)) + eps)
    assert learner.loss.log_alpha.item() == pytest.approx(la, rel=1e-5)
    assert learner.loss.alpha.item() == pytest.approx(math.exp(la), rel=1e-5)


def test_sapo_critic_fits_soft_targets_of_the_temperature_after_its_step():
    """The reference computes the critic targets after the temperature's step: the critic's
    minibatches carry the targets of the new alpha (not the window's)."""
    env = make_env("pendulum", num_envs=4, seed=0)
    config = SAPOConfig(horizon=4, critic_passes=1, critic_minibatches=1, critic_lr=1e-12, obs_norm=False)
    learner = SAPOLearner(env, make_sapo_actor(env, hidden=(8,)), tiny_twin_critic(env), config, 1000)
    windows, targets = [], []
    rollout, critic_loss = learner.collector.rollout, learner.loss.critic_loss
    learner.collector.rollout = lambda: windows.append(rollout()) or windows[-1]
    learner.loss.critic_loss = lambda batch: targets.append(batch["value_target"].clone()) or critic_loss(batch)
    metrics = learner.train_iteration()
    assert metrics["alpha"] != metrics["alpha_window"]
    window = windows[0].detach()
    expected = learner.loss.compute_value_targets(window).reshape(-1, 1)  # the new alpha, (almost) the same critics
    used = targets[0]
    order = torch.argsort(used.reshape(-1))
    torch.testing.assert_close(used.reshape(-1)[order], expected.reshape(-1)[torch.argsort(expected.reshape(-1))],
                               rtol=0, atol=1e-6)
    with torch.no_grad():
        learner.loss.log_alpha.fill_(math.log(metrics["alpha_window"]))
    stale = learner.loss.compute_value_targets(window.clone()).reshape(-1)
    assert (stale.sort().values - used.reshape(-1).sort().values).abs().max() > 1e-4


# ---------------------------------------------------------------------- the learners run
def test_ahac_learner_windows_follow_the_horizon_rule_on_pendulum():
    """Constant force 1500 (C = 500), dual lr 0.01: lambda = 10, 20, 30, 40 per step;
    H = 8 -> 8.8 -> 10.6 -> 13.9 -> 19.5: windows of 8, 9, 11, 14 steps."""
    env = pendulum_with_contact(num_envs=4, constant=1500.0)
    config = AHACConfig(horizon_lr=0.01, lr_schedule="constant", critic_passes=2, critic_minibatches=2)
    learner = AHACLearner(env, make_actor(env, hidden=(16,)), tiny_twin_critic(env), config, 10_000)
    lengths, horizons = [], []
    for _ in range(4):
        metrics = learner.train_iteration()
        lengths.append(learner.env_steps_per_iteration // 4)
        horizons.append(learner.adaptive_horizon.horizon)
        assert metrics["horizon"] == lengths[-1] and metrics["contact_force_max"] == pytest.approx(1500.0)
        assert math.isfinite(metrics["grad_norm_actor"]) and metrics["skipped_actor"] == 0
    assert lengths == [8, 9, 11, 14]
    assert horizons == pytest.approx([8.8, 10.6, 13.9, 19.5])


def test_ahac_learner_refuses_an_env_without_contact_forces():
    env = make_env("pendulum", num_envs=4, seed=0)
    learner = AHACLearner(env, make_actor(env, hidden=(8,)), tiny_twin_critic(env), AHACConfig(critic_passes=1))
    before = [p.detach().clone() for p in learner.actor_params]
    with pytest.raises(KeyError, match=r"no \('next', 'state', 'contact_force'\) entry; AHAC .* Hopper-v5"):
        learner.train_iteration()
    assert all(torch.equal(a, b) for a, b in zip(before, learner.actor_params))  # nothing was updated


def test_ahac_critic_fitting_stops_when_the_pass_losses_plateau():
    env = pendulum_with_contact(num_envs=8)
    config = AHACConfig(critic_plateau=1e9)  # the first check (after 5 passes) stops it
    learner = AHACLearner(env, make_actor(env, hidden=(8,)), tiny_twin_critic(env), config, 10_000)
    assert learner.train_iteration()["critic_passes"] == 6
    learner = AHACLearner(env, make_actor(env, hidden=(8,)), tiny_twin_critic(env),
                          AHACConfig(critic_plateau=1e-30, max_critic_passes=7), 10_000)
    assert learner.train_iteration()["critic_passes"] == 7


def test_critic_minibatches_in_order_are_time_blocks_of_the_window():
    """critic_shuffle=in_order (the references' unshuffled datasets): minibatch k holds steps
    [k H / M, (k + 1) H / M) of every env."""
    env = pendulum_with_contact(num_envs=4)
    config = AHACConfig(critic_passes=1, critic_minibatches=2)
    learner = AHACLearner(env, make_actor(env, hidden=(8,)), tiny_twin_critic(env), config, 10_000)
    windows, batches = [], []
    rollout, critic_loss = learner.collector.rollout, learner.loss.critic_loss
    learner.collector.rollout = lambda: windows.append(rollout()) or windows[-1]
    learner.loss.critic_loss = lambda batch: batches.append(batch["observation"].clone()) or critic_loss(batch)
    learner.train_iteration()
    obs = windows[0]["observation"].detach()  # [4, 8, 3]
    assert len(batches) == 2
    for k, batch in enumerate(batches):
        torch.testing.assert_close(batch, obs[:, 4 * k:4 * (k + 1)].transpose(0, 1).reshape(-1, obs.shape[-1]))


def test_ahac_resumes_its_horizon_from_a_state_dict():
    env = pendulum_with_contact(num_envs=4, constant=1500.0)
    config = AHACConfig(horizon_lr=0.01, lr_schedule="constant", critic_passes=1)
    learner = AHACLearner(env, make_actor(env, hidden=(8,)), tiny_twin_critic(env), config, 10_000)
    for _ in range(2):
        learner.train_iteration()
    state = learner.state_dict()
    other = AHACLearner(env, make_actor(env, hidden=(8,)), tiny_twin_critic(env), config, 10_000)
    other.load_state_dict(state)
    assert other.collector.horizon == 11 and other.adaptive_horizon.horizon == pytest.approx(10.6)
    other.train_iteration()
    assert other.env_steps_per_iteration == 4 * 11


@pytest.mark.parametrize("name", ["ahac", "sapo"])
def test_learner_state_dict_resumes_exactly(name):
    """Learner A trains 4 iterations; learner B loads A's state (and the random stream) after 2 and
    trains 2: the same weights, horizon and temperature."""
    def build():
        torch.manual_seed(0)
        env = pendulum_with_contact(num_envs=4)
        cfg = OmegaConf.create(LEARNERS[name].default_config()["loss"])
        extra = {"ahac": {"max_critic_passes": 3, "horizon_lr": 0.05}, "sapo": {"horizon": 4, "critic_passes": 2}}[name]
        return make_learner(OmegaConf.merge(cfg, {"actor": {"hidden": [8]}, "critic": {"hidden": [8]}, **extra}), env, 2000)

    a = build()
    for _ in range(2):
        a.train_iteration()
    state, rng = copy.deepcopy(a.state_dict()), torch.get_rng_state()
    metrics_a = [a.train_iteration() for _ in range(2)]
    b = build()
    b.load_state_dict(state)
    torch.set_rng_state(rng)
    metrics_b = [b.train_iteration() for _ in range(2)]
    assert metrics_a == metrics_b
    for pa, pb in zip(a.loss.parameters(), b.loss.parameters(), strict=True):
        assert torch.equal(pa, pb)
    if name == "ahac":
        assert a.adaptive_horizon.horizon == b.adaptive_horizon.horizon and a.collector.horizon == b.collector.horizon


@pytest.mark.parametrize("name", ["ahac", "sapo"])
def test_learners_run_on_hopper_with_finite_gradients(name):
    base = make_env("Hopper-v5", num_envs=4, seed=0)
    env = TransformedEnv(base, ContactForceFromState(base))
    cfg = OmegaConf.create(LEARNERS[name].default_config()["loss"])
    overrides = {"ahac": {"max_critic_passes": 3}, "sapo": {"horizon": 8, "critic_passes": 2}}[name]
    cfg = OmegaConf.merge(cfg, {"actor": {"hidden": [32, 32]}, "critic": {"hidden": [32]}, **overrides})
    learner = make_learner(cfg, env, 10_000)
    forces = []
    for _ in range(3):
        metrics = learner.train_iteration()
        forces.append(metrics["contact_force_max"])
        assert math.isfinite(metrics["grad_norm_actor"]) and metrics["grad_norm_actor"] > 0
        assert math.isfinite(metrics["loss_critic"]) and metrics["skipped_actor"] == 0
    assert max(forces) > 0  # the hopper stands on the floor
    for param in learner.actor_params + learner.critic_params:
        assert torch.isfinite(param).all()
    if name == "sapo":
        assert metrics["alpha"] != 1.0 and math.isfinite(metrics["entropy"])
    else:
        assert 8 <= metrics["horizon"] <= 64


# ---------------------------------------------------------------------- through the training script
TINY = ["logger=none", "train.progress_bar=false", "eval.gif=false", "env.num_envs=4", "env.max_episode_steps=12",
        "eval.num_envs=2", "eval.interval=1000000", "loss.actor.hidden=[16]", "loss.critic.hidden=[16]"]


def _compose(*overrides):
    import torchrl_diffenvs.training.config  # noqa: F401  (registers the env=<task> choices)

    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def test_sapo_trains_through_the_training_script(tmp_path, train_script):
    cfg = _compose("env=pendulum", "loss=sapo", *TINY, "loss.horizon=4", "loss.critic_passes=2",
                   "train.total_env_steps=32", "train.checkpoint_interval=32")
    script = train_script
    script.validate_config(cfg)
    result = script.run(cfg, tmp_path)
    assert result["env_steps"] == 32 and result["iterations"] == 2 and math.isfinite(result["eval/return"])
    assert (tmp_path / "checkpoints" / "last.pt").is_file()


def test_a_sapo_checkpoints_policy_loads_into_policy_from_config(tmp_path, train_script):
    """What evaluation must build for loss=sapo: the checkpoint's policy state loads exactly into
    SAPOLearner.policy_from_config (SHAC's actor_from_config has another head)."""
    from torchrl_diffenvs.modules import actor_from_config
    from torchrl_diffenvs.training import load_checkpoint

    cfg = _compose("env=pendulum", "loss=sapo", *TINY, "loss.horizon=4", "loss.critic_passes=1",
                   "train.total_env_steps=16", "train.checkpoint_interval=16")
    script = train_script
    script.run(cfg, tmp_path)
    ckpt = load_checkpoint(tmp_path / "checkpoints" / "last.pt")
    env = make_env("pendulum", num_envs=2, seed=0)
    policy = SAPOLearner.policy_from_config(OmegaConf.create(ckpt["config"]).loss, env)
    policy.load_state_dict(ckpt["policy"])
    with pytest.raises(RuntimeError, match="size mismatch"):
        actor_from_config(OmegaConf.create(ckpt["config"]).loss, env)[0].load_state_dict(ckpt["policy"])


def test_ahac_through_the_training_script_needs_an_env_with_contact_forces(tmp_path, train_script):
    """A one-line configuration error that names the envs AHAC can train on, before any run."""
    from torchrl_diffenvs.training import ConfigError

    cfg = _compose("env=pendulum", "loss=ahac", *TINY, "loss.max_critic_passes=2", "train.total_env_steps=64")
    script = train_script
    with pytest.raises(ConfigError, match="loss=ahac: env 'pendulum' reports no contact force .* Hopper-v5"):
        script.validate_config(cfg)
    with pytest.raises(ConfigError, match="reports no contact force"):
        script.run(cfg, tmp_path)


def test_ahac_trains_through_the_training_script_on_a_contact_task(tmp_path, train_script):
    """Hopper-v5 reports its contact force in its state: AHAC reads it, logs it and trains."""
    cfg = _compose("env=Hopper-v5", "loss=ahac", *TINY, "loss.max_critic_passes=2", "train.total_env_steps=64",
                   "train.checkpoint_interval=64", "logger=csv")
    result = train_script.run(cfg, tmp_path)
    assert result["env_steps"] >= 64 and math.isfinite(result["eval/return"])
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    forces = [row["train/contact_force_max"] for row in rows if "train/contact_force_max" in row]
    horizons = [row["train/horizon"] for row in rows if "train/horizon" in row]
    assert forces and all(f >= 0 for f in forces) and max(forces) > 0
    assert horizons and all(8 >= h >= 4 for h in horizons)
