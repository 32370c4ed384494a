"""Short seeded learning checks on the Ivy-style Pendulum (default physics, 100-step episodes).

Reference points (mean per-step reward of 100-step episodes from random starts): a policy of
uniformly random actions scores about 0.45 (measured in each test); an untrained network 0.35-0.5;
a hand-written energy-pumping + PD swing-up controller 0.75 (the swing-up from the bottom takes
several seconds with this motor, so no policy gets near 1). Gradient learners first sit on a
plateau near 0.49 (the pendulum is left swinging) and then learn to pump energy; a policy scoring
above 0.6 swings the pendulum up from most starts.
"""
import math

import pytest
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from torchrl_diffenvs import make_env
from torchrl_diffenvs.evaluation import evaluate
from torchrl_diffenvs.learners import BPTTConfig, BPTTLearner, SHACConfig, SHACLearner
from torchrl_diffenvs.modules import ObservationNormalizer, make_actor, make_critic
from torchrl_diffenvs.open_loop import OpenLoopActor


class UniformRandomPolicy(TensorDictModuleBase):
    def __init__(self, env, seed=0):
        super().__init__()
        self.in_keys, self.out_keys = ["observation"], ["action"]
        self.env, self.gen = env, torch.Generator().manual_seed(seed)

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        td.set("action", torch.rand(self.env.num_envs, self.env.action_dim, generator=self.gen) * 2 - 1)
        return td


@pytest.fixture(scope="module")
def eval_env():
    return make_env("pendulum", num_envs=128, seed=1234)


@pytest.fixture(scope="module")
def random_policy_reward(eval_env):
    return evaluate(eval_env, UniformRandomPolicy(eval_env))["reward_mean"]


def test_trajectory_optimisation_swings_the_pendulum_up():
    """Ivy's optimize_trajectory: an open-loop table from the bottom at rest, full-episode BPTT."""
    torch.manual_seed(0)
    env = make_env("pendulum", num_envs=1, seed=0, max_episode_steps=100)
    start = env.reset()
    start["state", "th"] = torch.tensor([math.pi])  # hanging down, at rest: reward ~0
    start["state", "thd"] = torch.tensor([0.0])
    actor = OpenLoopActor.from_env(env, generator=torch.Generator().manual_seed(0))
    settings = BPTTConfig(horizon=100, actor_lr=0.1, betas=(0.9, 0.999), lr_schedule="constant", max_grad_norm=None)
    learner = BPTTLearner(env, actor, settings, total_env_steps=2500, start_state=start)
    returns = [learner.train_iteration()["reward"] * 100 for _ in range(25)]
    assert returns[0] < 1.0
    assert max(returns[-5:]) > 15.0, returns  # the pendulum gets well above the horizontal


def test_bptt_learns_to_swing_up(eval_env, random_policy_reward):
    """BPTT over 16-step windows with carried state, Ivy's deterministic tanh policy, N=64."""
    torch.manual_seed(0)
    env = make_env("pendulum", num_envs=64, seed=0)
    normalizer = ObservationNormalizer(env.observation_dim)
    actor = make_actor(env, distribution="deterministic", normalizer=normalizer)
    learner = BPTTLearner(env, actor, BPTTConfig(horizon=16, actor_lr=1e-2), total_env_steps=1000 * 64 * 16,
                          normalizer=normalizer)
    before = evaluate(eval_env, actor)["reward_mean"]
    for _ in range(160):
        learner.train_iteration()
    after = evaluate(eval_env, actor)["reward_mean"]
    assert random_policy_reward < 0.5 and before < 0.5
    assert after > 0.6, (random_policy_reward, before, after)


def test_shac_learns_to_swing_up(eval_env, random_policy_reward):
    """SHAC: 16-step windows closed by the target critic, TanhNormal policy, N=64."""
    torch.manual_seed(0)
    env = make_env("pendulum", num_envs=64, seed=0)
    normalizer = ObservationNormalizer(env.observation_dim)
    actor = make_actor(env, normalizer=normalizer)
    settings = SHACConfig(horizon=16, actor_lr=1e-2, critic_passes=2, critic_minibatches=2)
    learner = SHACLearner(env, actor, make_critic(env, normalizer=normalizer), settings,
                          total_env_steps=1000 * 64 * 16, normalizer=normalizer)
    before = evaluate(eval_env, actor)["reward_mean"]
    for _ in range(140):
        learner.train_iteration()
    after = evaluate(eval_env, actor)["reward_mean"]
    assert random_policy_reward < 0.5 and before < 0.5
    assert after > 0.6, (random_policy_reward, before, after)


@pytest.mark.parametrize("script, extra", [
    ("optimize_trajectory", ["env=reacher", "steps=10"]),
    ("optimize_policy", ["env=swimmer", "steps=10", "loss=shac", "policy=stochastic", "num_envs=4", "eval_envs=4",
                         "gif_envs=2", "eval_every=1"]),
])
def test_demo_scripts_write_a_learning_curve_and_a_gif(tmp_path, monkeypatch, script, extra):
    """The Ivy demos end to end with tiny settings (the learning itself is checked above)."""
    pytest.importorskip("matplotlib")
    pytest.importorskip("PIL")
    import importlib
    import sys
    from pathlib import Path

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[2] / "sota_scripts"))
    module = importlib.import_module(script)
    summary = module.main(["iterations=2", f"out_dir={tmp_path}", "progress=false", *extra])
    gif = "trajectory.gif" if script == "optimize_trajectory" else "policy.gif"
    assert (tmp_path / "learning_curve.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / gif).read_bytes()[:6] == b"GIF89a"
    assert summary["iterations"] == 2 and summary["skipped_steps"] == 0
    with pytest.raises(SystemExit, match="unknown argument"):
        module.main(["nonsense=1"])
    not_created = tmp_path / "not_created"
    with pytest.raises(SystemExit, match="env='Swimmer': valid: .*swimmer"):
        module.main(["env=Swimmer", f"out_dir={not_created}"])
    if script == "optimize_policy":
        with pytest.raises(SystemExit, match="loss='ppo': valid: bptt, shac"):
            module.main(["loss=ppo", f"out_dir={not_created}"])
    with pytest.raises(SystemExit, match="iterations: Value 'two' of type 'str' could not be converted to Integer"):
        module.main(["iterations=two", f"out_dir={not_created}"])
    assert not not_created.exists()
    sys.modules.pop(script, None)


def test_system_identification_recovers_edited_masses_and_damping(tmp_path, monkeypatch):
    """The demo end to end, small: MuJoCo (gymnasium's env) records a model file whose masses and
    damping were edited; our model, fitted by L-BFGS through autograd, recovers them."""
    pytest.importorskip("mujoco")
    pytest.importorskip("matplotlib")
    import importlib
    from pathlib import Path

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[2] / "sota_scripts"))
    module = importlib.import_module("system_identification")
    # one-step segments: half the physics per loss evaluation of the default two (the fit's cost is
    # the 20 RK4 stages per env step, not the batch); recovered to 1e-8 in five L-BFGS steps
    summary = module.main(["trajectories=3", "steps=8", "segment=1", "iterations=5", "true_mass=7,5,2",
                           "true_damping=0.4,0.2,0.3", f"out_dir={tmp_path}", "progress=false"])
    assert 'mass="7.0"' in (tmp_path / "edited_model.xml").read_text()
    by_name = {p["name"]: p for p in summary["parameters"]}
    assert by_name["mass cart"]["true"] == 7.0 and by_name["damping hinge2"]["true"] == 0.3
    for p in summary["parameters"]:
        assert p["relative_error"] < 1e-5, p
        assert abs(p["initial"] - p["true"]) / p["true"] > 0.1  # the fit had something to find
    assert summary["loss"][-1] < 1e-12 * summary["loss"][0]
    not_created = tmp_path / "not_created"
    with pytest.raises(SystemExit, match="true_mass='1,2': expected 3 positive comma-separated numbers"):
        module.main(["true_mass=1,2", f"out_dir={not_created}"])
    with pytest.raises(SystemExit, match="steps >= segment"):
        module.main(["steps=1", "segment=2", f"out_dir={not_created}"])
    assert not not_created.exists()
