"""One non-finite env must not stop the others from learning.

References: the same rollout without the non-finite env (a batch of the 15 finite envs started
from the same states: its loss and its gradient), hand-computed losses, and the env indices the
test poisoned itself. The NaN is written into ``env.params`` after construction (a physical
parameter that became NaN); the env's own ``("next", "nonfinite")`` flag is simulated by
writing it into a window.
"""
import math
import warnings

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType

from torchrl_diffenvs import make_env
from torchrl_diffenvs.collectors import DiffWindowCollector
from torchrl_diffenvs.envs.multi_agent import policy_keys
from torchrl_diffenvs.learners import LEARNERS, make_learner
from torchrl_diffenvs.modules import make_actor, make_critic
from torchrl_diffenvs.objectives import (
    BPTTLoss,
    GradientGuard,
    NonFiniteEnvMonitor,
    NonFiniteEnvWarning,
    NonFiniteTrainingError,
    SHACLoss,
    nonfinite_envs,
)

N, BAD, H = 16, 3, 5
KEEP = [i for i in range(N) if i != BAD]


def poisoned_pendulum(bad=(BAD,), dtype=torch.float32, seed=0):
    env = make_env("pendulum", num_envs=N, seed=seed, dtype=dtype, max_episode_steps=50)
    for i in bad:
        env.params["mass"][i] = float("nan")  # in place: every later reset and step reads it
    return env


SMALL = {
    "bptt": {"horizon": H, "obs_norm": True},
    "shac": {"horizon": H, "obs_norm": True},
    "ppo": {"rollout_len": H, "minibatch_size": 16, "epochs": 2, "obs_norm": True},
    "sac": {"rollout_len": 2, "init_random_frames": 0, "batch_size": 8, "buffer_size": 256},
    "sapo": {"horizon": H, "obs_norm": True, "critic_passes": 2},
    "ahac": {"min_horizon": 4, "max_horizon": 6, "critic_passes": 2},
}


def learner_for(loss, env):
    torch.manual_seed(0)
    cfg = OmegaConf.create(LEARNERS[loss].default_config()["loss"])
    for network in ("actor", "critic", "qvalue"):
        if network in cfg:
            cfg[network].hidden = [16]
    return make_learner(OmegaConf.merge(cfg, SMALL[loss]), env, 100_000)


# ---------------------------------------------------------------------- the losses, against the 15 finite envs
def _windows(loss_name):
    """The same deterministic window collected on the 16 envs (env 3 NaN) and on the 15 finite
    ones started from the same states, with one actor (and critic): float64."""
    torch.manual_seed(1)
    env16 = poisoned_pendulum(dtype=torch.float64)
    env15 = make_env("pendulum", num_envs=N - 1, seed=0, dtype=torch.float64, max_episode_steps=50)
    start = env16.reset()
    actor = make_actor(env16, hidden=(16,))
    critic = make_critic(env16, hidden=(16,))  # one critic for both windows

    def make_loss():
        return BPTTLoss(actor) if loss_name == "bptt" else SHACLoss(actor, critic, gamma=0.9, lmbda=0.8)
    out = []
    for env, state in ((env16, start), (env15, start[KEEP])):
        collector = DiffWindowCollector(env, actor, horizon=H, start_state=state,
                                        exploration_type=ExplorationType.DETERMINISTIC)
        window = collector.rollout()
        loss = make_loss()
        value = loss(window)
        actor.zero_grad(set_to_none=True)
        value["loss_actor"].backward()
        grads = [p.grad.clone() for p in actor.parameters() if p.grad is not None]
        out.append((window, value, grads, collector))
    return out


@pytest.mark.parametrize("loss_name", ["bptt", "shac"])
def test_loss_and_gradient_equal_those_of_the_finite_envs_alone(loss_name):
    (window, out, grads, collector), (ref_window, ref_out, ref_grads, _) = _windows(loss_name)
    reward = window["next", "reward"].squeeze(-1)
    flagged = window["next", "nonfinite"].squeeze(-1)
    # the poisoned env is flagged by the env, which zeroes its NaN rewards; the others are not
    assert flagged[BAD, 1:].all() and not flagged[KEEP].any() and (reward[BAD, 1:] == 0).all()
    torch.testing.assert_close(reward[KEEP], ref_window["next", "reward"].squeeze(-1))  # same rollout otherwise
    assert collector.nonfinite.nonzero().flatten().tolist() == [BAD]
    assert window["isolated"][BAD].all() and not window["isolated"][KEEP].any()
    assert out["nonfinite_envs"] == 1 and ref_out["nonfinite_envs"] == 0
    if loss_name == "bptt":  # hand-computed: minus the mean reward of the 15 finite envs
        torch.testing.assert_close(out["loss_actor"], -reward[KEEP].sum() / ((N - 1) * H))
    torch.testing.assert_close(out["loss_actor"], ref_out["loss_actor"])
    torch.testing.assert_close(out["reward_mean"], ref_out["reward_mean"])
    assert len(grads) == len(ref_grads) > 0
    for grad, ref in zip(grads, ref_grads):
        assert torch.isfinite(grad).all()
        torch.testing.assert_close(grad, ref)
    # a flagged env is terminated and restarts: the policy reads its fresh, finite start observations
    assert torch.isfinite(window["observation"][BAD]).all()


def test_the_envs_own_nonfinite_flag_leaves_it_out_of_the_loss():
    reward = torch.tensor([[1.0, 2.0], [3.0, 5.0], [10.0, 20.0]])
    window = TensorDict({"next": {"reward": reward.unsqueeze(-1), "done": torch.zeros(3, 2, 1, dtype=torch.bool),
                                  "nonfinite": torch.tensor([[False], [False], [False], [True], [False], [False]]
                                                            ).reshape(3, 2, 1)}}, batch_size=[3, 2])
    out = BPTTLoss(torch.nn.Linear(1, 1))(window)
    assert out["nonfinite_envs"] == 1
    assert out["loss_actor"].item() == pytest.approx(-(1 + 2 + 10 + 20) / 4)
    assert nonfinite_envs(window).tolist() == [False, True, False]


# ---------------------------------------------------------------------- the learners
@pytest.mark.parametrize("loss", ["bptt", "shac", "ppo", "sac", "sapo"])
def test_one_nan_env_out_of_16_no_longer_stops_learning(loss):
    learner = learner_for(loss, poisoned_pendulum())
    params = list(learner.actor.parameters())
    before = [p.detach().clone() for p in params]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        history = [learner.train_iteration() for _ in range(3)]
    for metrics in history:
        assert metrics["nonfinite_envs"] == 1
        assert all(v == 0 for k, v in metrics.items() if k.startswith("skipped")), metrics
        losses = {k: v for k, v in metrics.items() if k.startswith("loss")}
        assert losses and all(torch.isfinite(torch.tensor(v)) for v in losses.values()), metrics
        assert torch.isfinite(torch.tensor(metrics["reward"]))
    assert all(torch.isfinite(p).all() for p in params)
    assert any(not torch.equal(a, b) for a, b in zip(before, params))  # the actor learned
    # one warning naming env 3 for the whole burst (it stays NaN), none for the finite envs
    reports = [str(w.message) for w in caught if issubclass(w.category, NonFiniteEnvWarning)]
    assert len(reports) == 1 and f"env(s) [{BAD}] of {N}" in reports[0], reports
    assert "non-finite physical parameters or a diverging simulation" in reports[0]
    if learner.__dict__.get("normalizer") is not None:
        assert torch.isfinite(learner.normalizer.mean).all() and learner.normalizer.count > 0


def test_ppo_trains_on_exactly_the_finite_envs():
    learner = learner_for("ppo", poisoned_pendulum())
    seen = []
    step = learner.gradient_step
    learner.gradient_step = lambda batch: (seen.append(batch.clone()), step(batch))[1]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NonFiniteEnvWarning)
        learner.train_iteration()
    per_epoch = sum(batch.numel() for batch in seen) // learner.config.epochs
    assert per_epoch == (N - 1) * H  # every finite transition once per epoch, the NaN env's never
    for batch in seen:
        for key in ("observation", ("next", "observation"), ("next", "reward"), "advantage", "value_target"):
            assert torch.isfinite(batch[key]).all(), key


def test_sac_replay_buffer_holds_finite_transitions_only():
    learner = learner_for("sac", poisoned_pendulum())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NonFiniteEnvWarning)
        for _ in range(3):
            learner.train_iteration()
    stored = learner.buffer[:]
    assert len(learner.buffer) == 3 * (N - 1) * 2
    for key in learner.buffer_keys:
        value = stored[key]
        if value.dtype.is_floating_point:
            assert torch.isfinite(value).all(), key
    assert torch.isfinite(learner.loss.log_alpha).all()


@pytest.mark.parametrize("loss", ["bptt", "shac", "ppo", "sac", "sapo"])
def test_repeated_nonfinite_updates_raise_naming_the_cause_and_the_envs(loss):
    learner = learner_for(loss, poisoned_pendulum(bad=range(N)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NonFiniteEnvWarning)
        with pytest.raises(NonFiniteTrainingError, match=(
                r"20 consecutive updates skipped because the loss or gradient was NaN/inf \(env\(s\) \[0, 1, 2, .*\] of "
                r"16 were non-finite.*non-finite physical parameters .* or a diverging simulation")):
            for _ in range(25):
                learner.train_iteration()


# ---------------------------------------------------------------------- the building blocks
def test_gradient_guard_raises_after_consecutive_nonfinite_skips_only():
    p = torch.nn.Parameter(torch.zeros(2, dtype=torch.float64))
    guard = GradientGuard(max_norm=None, skip_above=10.0, max_nonfinite_skips=3)
    optimizer = torch.optim.SGD([p], lr=1.0)

    def step(grad, loss=0.0):
        p.grad = torch.tensor(grad, dtype=torch.float64)
        return guard.step(optimizer, loss=loss, context=lambda: "env(s) [7] of 8 were non-finite")

    for grad in ([float("nan"), 0.0], [0.0, float("inf")]):
        assert step(grad)["skipped"]
    assert step([100.0, 0.0])["skipped"]  # a huge finite norm is skipped but is no NaN: it resets the count
    assert guard.nonfinite_in_a_row == 0
    assert step([0.0, 0.0], loss=float("nan"))["skipped"] and step([float("nan"), 0.0])["skipped"]
    with pytest.raises(NonFiniteTrainingError, match=r"^3 consecutive .* \(env\(s\) \[7\] of 8 were non-finite\)"):
        step([float("nan"), 0.0])
    torch.testing.assert_close(p.detach(), torch.zeros(2, dtype=torch.float64))  # never stepped
    assert GradientGuard(max_nonfinite_skips=None).max_nonfinite_skips is None
    with pytest.raises(ValueError, match="max_nonfinite_skips must be a positive integer or None, got 0"):
        GradientGuard(max_nonfinite_skips=0)
    # older checkpoints have no count: it starts at 0
    guard.load_state_dict({"skipped": 4, "steps": 5})
    assert guard.nonfinite_in_a_row == 0 and guard.skipped == 4


def test_monitor_warns_once_per_burst_with_the_indices():
    monitor = NonFiniteEnvMonitor("SHACLearner")

    def update(indices, iteration):
        bad = torch.zeros(8, dtype=torch.bool)
        bad[list(indices)] = True
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            count = monitor.update(bad, iteration)
        return count, [str(w.message) for w in caught]

    count, messages = update([2], 0)
    assert count == 1 and len(messages) == 1 and messages[0].startswith("SHACLearner: env(s) [2] of 8")
    assert "iteration 0" in messages[0]
    assert update([2], 1) == (1, [])  # the same burst
    count, messages = update([2, 5], 2)  # a new env joins: reported with all current ones
    assert count == 2 and len(messages) == 1 and "env(s) [2, 5] of 8" in messages[0]
    assert update([], 3) == (0, [])
    assert monitor.describe() == "every env's rewards and observations were finite in the latest rollout"
    count, messages = update([2], 4)  # a new burst
    assert len(messages) == 1 and "iteration 4" in messages[0]
    assert monitor.describe() == "env(s) [2] of 8 were non-finite in the latest rollout"


def test_collector_isolation_can_be_turned_off():
    env = poisoned_pendulum()
    collector = DiffWindowCollector(env, make_actor(env, hidden=(8,)), horizon=3, isolate_nonfinite=False)
    window = collector.rollout()
    assert collector.nonfinite.nonzero().flatten().tolist() == [BAD]  # still found and marked for the losses
    assert window["isolated"][BAD].all()
    assert policy_keys(env).observation == "observation"


def test_compiled_rollout_chunks_skip_the_update_with_a_nonfinite_env():
    """``compile_physics``: the chunks run without the gradient hooks (documented in
    IsolatingPolicy), so the window's gradient is NaN and BPTT skips the update; the env is still
    found, counted and reported, and the compiled windows do not recompile for it."""
    from torchrl_diffenvs import compile_physics
    from torchrl_diffenvs.learners import BPTTConfig, BPTTLearner

    torch.compiler.reset()
    env = poisoned_pendulum()
    compile_physics(env, steps_per_chunk=H, backend="aot_eager")
    torch.manual_seed(0)
    learner = BPTTLearner(env, make_actor(env, hidden=(16,)), BPTTConfig(horizon=H), 100_000)
    with pytest.warns(NonFiniteEnvWarning, match=rf"env\(s\) \[{BAD}\] of {N}"):
        metrics = learner.train_iteration()
    assert metrics["nonfinite_envs"] == 1 and metrics["skipped_actor"] == 1
    assert torch.isfinite(torch.tensor(metrics["loss_actor"]))  # the loss itself is the finite envs'
    torch.compiler.reset()


@pytest.mark.parametrize("loss", ["bptt", "shac", "ppo"])
def test_a_nan_env_of_a_multi_agent_env_is_isolated(loss):
    """Per-agent observations, rewards and actions ``[N, A, ...]``: the env (all its agents) is left out."""
    env = make_env("multi_swimmer", num_envs=8, seed=0)
    env.params["dt"][2] = float("nan")
    learner = learner_for(loss, env)
    before = [p.detach().clone() for p in learner.actor.parameters()]
    with pytest.warns(NonFiniteEnvWarning, match=r"env\(s\) \[2\] of 8"):
        metrics = [learner.train_iteration() for _ in range(2)][-1]
    assert metrics["nonfinite_envs"] == 1
    assert all(v == 0 for k, v in metrics.items() if k.startswith("skipped")), metrics
    assert all(torch.isfinite(torch.tensor(v)) for k, v in metrics.items() if k.startswith("loss")), metrics
    assert any(not torch.equal(a, b.detach()) for a, b in zip(before, learner.actor.parameters()))


@pytest.mark.skipif(not torch.distributed.is_available(), reason="torch.distributed is not available")
def test_a_nan_env_on_one_rank_keeps_the_ranks_in_step(tmp_path):
    """2 gloo ranks, a NaN env on rank 1 only, for each of BPTT, SHAC, PPO and SAC (in one pair of
    processes): no hang (the ranks' exchanges still match), both ranks learn, and their weights
    stay identical."""
    import torch.multiprocessing as mp

    import _nonfinite_workers as workers

    store, out, losses = tmp_path / "store", tmp_path / "out", ["bptt", "shac", "ppo", "sac"]
    out.mkdir()
    mp.spawn(workers.train_with_a_nan_env_on_rank_1, args=(2, str(store), str(out), losses, 3), nprocs=2, join=True)
    for loss in losses:
        ranks = [torch.load(out / f"rank{r}_{loss}.pt", weights_only=False) for r in range(2)]
        assert [m["nonfinite_envs"] for m in ranks[0]["metrics"]] == [0, 0, 0], loss
        assert [m["nonfinite_envs"] for m in ranks[1]["metrics"]] == [1, 1, 1], loss
        for rank in ranks:
            last = rank["metrics"][-1]
            assert all(v == 0 for k, v in last.items() if k.startswith("skipped")), (loss, last)
            assert all(torch.isfinite(torch.tensor(v)) for k, v in last.items() if k.startswith("loss")), (loss, last)
        for a, b in zip(ranks[0]["actor"], ranks[1]["actor"]):
            assert torch.isfinite(a).all(), loss
            torch.testing.assert_close(a, b, rtol=0, atol=0, msg=lambda m: f"{loss}: {m}")


def test_ahac_leaves_a_nan_env_out_of_its_loss_critics_and_horizon():
    """AHAC on HalfCheetah with one env's masses NaN: the actor and critics learn from the others,
    the env is counted, and the adaptive horizon (fed by the contact forces) stays finite."""
    env = make_env("HalfCheetah-v5", num_envs=N, seed=0, max_episode_steps=50)
    env.params["body_mass"][BAD] = float("nan")
    learner = learner_for("ahac", env)
    params = list(learner.actor.parameters())
    before = [p.detach().clone() for p in params]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NonFiniteEnvWarning)
        history = [learner.train_iteration() for _ in range(3)]
    for metrics in history:
        assert metrics["nonfinite_envs"] == 1
        assert all(v == 0 for k, v in metrics.items() if k.startswith("skipped")), metrics
        assert all(math.isfinite(metrics[k]) for k in ("loss_actor", "loss_critic", "horizon_next", "horizon_dual"))
    assert all(torch.isfinite(p).all() for p in params)
    assert any(not torch.equal(a, b) for a, b in zip(before, params))
