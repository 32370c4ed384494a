"""Every assumption ``torchrl_diffenvs/_compat.py`` makes about TorchRL's, tensordict's and torch's
private names, checked against the installed versions: after an upgrade, a failure here names
the assumption that broke (instead of a wrong result somewhere else)."""
import importlib.metadata

import torch
from tensordict import TensorDict
from tensordict.nn import InteractionType, set_interaction_type
from torch.distributions import Normal
from torchrl.collectors import Collector
from torchrl.envs import EnvBase

from torchrl_diffenvs import _compat, make_env
from torchrl_diffenvs.modules import make_actor


def test_installed_versions_are_those_compat_was_checked_against():
    """Same major.minor as CHECKED_VERSIONS: a new TorchRL/tensordict/torch minor release means
    re-checking every assumption below (and updating CHECKED_VERSIONS), not trusting it silently."""
    for package, checked in _compat.CHECKED_VERSIONS.items():
        installed = importlib.metadata.version(package).split("+")[0]
        assert installed.split(".")[:2] == checked.split(".")[:2], (
            f"_compat.py was checked with {package} {checked}; {installed} is installed: run tests/project/test_compat.py "
            "and the fast-rollout parity tests, then update CHECKED_VERSIONS")


def test_envbase_still_has_the_private_methods_the_lean_rollout_reimplements():
    for name in _compat.ENVBASE_STEP_METHODS:
        assert callable(getattr(EnvBase, name, None)), f"EnvBase.{name} is gone: update torchrl_diffenvs/envs/rollout"


def test_rollout_machinery_flags_are_where_torchrl_puts_them():
    env = make_env("pendulum", num_envs=2, seed=0)
    assert _compat.rollout_machinery_in_use(env) is None
    assert _compat.has_dynamic_specs(env) is False
    env.compile()  # EnvBase.compile stores its compiled step in __dict__["_compiled_step_and_maybe_reset"]
    assert _compat.rollout_machinery_in_use(env) == "env.compile() is active"
    env.eager()
    assert _compat.rollout_machinery_in_use(env) is None
    assert hasattr(env, "_post_step_mdp_hooks"), "EnvBase._post_step_mdp_hooks is gone: update _compat.py"


def test_make_compatible_policy_wraps_a_plain_callable():
    env = make_env("pendulum", num_envs=2, seed=0)

    def policy(td):
        return td.set("action", torch.zeros(2, 1))

    wrapped = _compat.make_compatible_policy(policy, env, trust_policy=False)
    out = wrapped(env.reset())
    assert torch.equal(out["action"], torch.zeros(2, 1))


def test_unchecked_tensordict_equals_the_checked_constructor():
    source = {"a": torch.ones(3, 2), "b": TensorDict({"c": torch.zeros(3)}, batch_size=[3])}
    fast = _compat.unchecked_tensordict(dict(source), torch.Size([3]), None)
    assert (fast == TensorDict(source, batch_size=[3])).all()
    assert fast.batch_size == torch.Size([3])


def test_interaction_type_and_sampler_generator_probes():
    env = make_env("pendulum", num_envs=2, seed=0)
    actor = make_actor(env)
    with set_interaction_type(InteractionType.RANDOM):
        assert _compat.current_interaction_type() is InteractionType.RANDOM
    sampler = actor.module[-1]
    assert not _compat.sampler_has_own_generator(sampler)
    assert hasattr(sampler, "_generator"), "ProbabilisticTensorDictModule._generator is gone: update _compat.py"


def test_standard_normal_is_the_noise_of_normal_rsample():
    loc, scale = torch.zeros(5, dtype=torch.float64), torch.full((5,), 2.0, dtype=torch.float64)
    torch.manual_seed(0)
    expected = Normal(loc, scale).rsample()
    torch.manual_seed(0)
    assert torch.equal(loc + _compat.standard_normal(loc.shape, loc.dtype, loc.device) * scale, expected)


def test_collector_carrier_holds_the_env_state_to_resume_from():
    env = make_env("pendulum", num_envs=2, seed=0)
    collector = Collector(env, make_actor(env), frames_per_batch=4, total_frames=-1,
                          auto_register_policy_transforms=False)
    next(iter(collector))
    state = _compat.collector_carrier_state(collector)
    assert state is not None, "Collector._carrier is gone: resume would restart episodes"
    assert ("state", "th") in TensorDict(state["data"], batch_size=state["batch_size"]).keys(True)
    state["data"]["state"]["th"] = torch.tensor([0.25, -0.5])
    _compat.load_collector_carrier(collector, state)
    assert torch.equal(collector._carrier["state", "th"], torch.tensor([0.25, -0.5]))
    collector.shutdown(close_env=False)


def test_compile_errors_cover_backend_failures():
    """The compiled rollout chunks fall back to eager on these (tests/rollout/test_compiled_rollout.py)."""
    assert issubclass(torch._dynamo.exc.BackendCompilerFailed, _compat.COMPILE_ERRORS)
    assert issubclass(torch._dynamo.exc.Unsupported, _compat.COMPILE_ERRORS)
