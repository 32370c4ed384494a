"""Per-env random streams: env ``i``'s start states depend on (seed, ``i``, its own episode
count) only -- not on the batch size, not on how often the other envs reset.

References: the same env in a batch of another size; a second env with the same seed whose
other envs were (or were not) reset in between; the distribution of the samplers (moments of
U[0, 1) and N(0, 1) over many draws).
"""

import pytest
import torch

from torchrl_diffenvs import make_env
from torchrl_diffenvs.envs.streams import StartDraw, seed_key

# the tasks whose start states are random (uniform and normal samplers, a rejection loop: swimmer)
TASKS = ["CartPole-v1", "Hopper-v5", "Walker2d-v5", "InvertedPendulum-v5", "InvertedDoublePendulum-v5",
         "pendulum", "swimmer", "Reacher-v5"]


def start_state(td, index):
    return {key: value[index] for key, value in td["state"].items()}


def assert_same_states(a: dict, b: dict, what: str):
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), f"{what}: state entry {key!r} differs"


def partial_reset(env, td, envs):
    td = td.clone()
    mask = torch.zeros(env.num_envs, 1, dtype=torch.bool)
    mask[list(envs)] = True
    td.set("_reset", mask)
    return env.reset(td, set_state=False)


@pytest.mark.parametrize("name", TASKS)
def test_env_i_of_a_batch_of_64_equals_env_i_of_a_batch_of_8(name):
    big, small = make_env(name, num_envs=64, seed=11), make_env(name, num_envs=8, seed=11)
    for episode in range(2):  # the first two episodes of every env
        td_big, td_small = big.reset(), small.reset()
        assert_same_states(start_state(td_big, slice(0, 8)), start_state(td_small, slice(None)), f"episode {episode}")
        assert torch.equal(td_big["observation"][:8], td_small["observation"])
    # and the envs of a batch differ from each other
    assert not torch.equal(td_big["observation"][0], td_big["observation"][1])


@pytest.mark.parametrize("name", TASKS)
def test_resetting_env_3_alone_leaves_env_5s_later_start_states(name):
    busy, quiet = make_env(name, num_envs=8, seed=5), make_env(name, num_envs=8, seed=5)
    td_busy, td_quiet = busy.reset(), quiet.reset()
    before = start_state(td_busy, 3)
    for _ in range(3):  # env 3 restarts three times in the busy env only
        td_busy = partial_reset(busy, td_busy, [3])
    assert not torch.equal(td_busy["observation"][3], td_quiet["observation"][3]), "env 3 should move on"
    assert torch.equal(busy.episodes, torch.tensor([1, 1, 1, 4, 1, 1, 1, 1]))
    # env 5's next start state, and the one after, are the same in both
    for _ in range(2):
        td_busy, td_quiet = partial_reset(busy, td_busy, [5]), partial_reset(quiet, td_quiet, [5])
        assert_same_states(start_state(td_busy, 5), start_state(td_quiet, 5), "env 5 after env 3's resets")
    # the envs that were not reset keep their state (TorchRL merges only the reset envs)
    assert_same_states(start_state(td_busy, 0), start_state(td_quiet, 0), "env 0")
    # env 3's fourth start state is the one a fresh env draws at its episode 3
    fresh = make_env(name, num_envs=8, seed=5)
    fresh.episodes = torch.full((8,), 3)
    assert_same_states(start_state(td_busy, 3), start_state(fresh.reset(), 3), "env 3 at episode 3")
    assert not all(torch.equal(before[k], td_busy["state"][k][3]) for k in before)


@pytest.mark.parametrize("name", ["CartPole-v1", "pendulum", "Hopper-v5"])
def test_reproducible_for_a_seed_and_different_across_seeds(name):
    a, b, c = (make_env(name, num_envs=4, seed=s) for s in (1, 1, 2))
    td_a, td_b, td_c = a.reset(), b.reset(), c.reset()
    assert_same_states(start_state(td_a, slice(None)), start_state(td_b, slice(None)), "same seed")
    assert not torch.equal(td_a["observation"], td_c["observation"])
    # set_seed starts the streams over
    a.reset()
    a.set_seed(1)
    assert torch.equal(a.reset()["observation"], td_a["observation"])


def test_rollouts_are_the_same_per_env_whatever_the_batch_and_the_other_envs():
    """Auto-resets inside a rollout: with a policy that reads only its own env's observation,
    env i's trajectory is the same in a batch of 3 and of 7, although env 0 (here terminating at
    other times, off balance) resets at other steps than the rest."""
    def policy(td):
        return td.set("action", torch.tanh(td["observation"][..., :1] * 3))

    outs = []
    for n in (3, 7):
        env = make_env("CartPole-v1", num_envs=n, seed=2, max_episode_steps=9)
        td = env.reset()
        td["state"].apply_(lambda x: x * 1.0)
        outs.append(env.rollout(30, policy, break_when_any_done=False))
    small, big = outs
    assert small["next", "done"].sum() >= 6, "want several resets per env"
    for key in ("observation", ("next", "observation"), ("next", "reward"), ("next", "done")):
        assert torch.equal(big[key][:3], small[key]), key


def test_the_samplers_have_the_right_distribution():
    draw = StartDraw(seed_key(123), torch.arange(4000), torch.zeros(4000, dtype=torch.int64))
    for dtype in (torch.float32, torch.float64):
        u = draw.uniform((4000, 25), dtype)
        assert u.dtype == dtype and bool((u >= 0).all()) and bool((u < 1).all())
        assert abs(u.mean().item() - 0.5) < 0.005 and abs(u.var().item() - 1 / 12) < 0.002
        z = draw.normal((4000, 25), dtype)
        assert abs(z.mean().item()) < 0.02 and abs(z.std().item() - 1) < 0.02
        # neighbouring envs, elements and draws are uncorrelated
        for a, b in ((u[1:, 0], u[:-1, 0]), (u[:, 1], u[:, 0])):
            assert abs(torch.corrcoef(torch.stack([a, b]))[0, 1].item()) < 0.05
    # the tails: P(|z| > 3) = 0.0027
    z = draw.normal((4000, 100), torch.float64)
    assert abs((z.abs() > 3).double().mean().item() - 0.0027) < 0.0007
    # distinct episodes of one env give distinct numbers
    a = StartDraw(seed_key(123), torch.zeros(2, dtype=torch.int64), torch.tensor([0, 1])).uniform((2, 8), torch.float64)
    assert not torch.equal(a[0], a[1])
    assert seed_key(1) == seed_key(1) and seed_key(1) != seed_key(2)


def test_start_state_samplers_need_one_row_per_env():
    env = make_env("pendulum", num_envs=3, seed=0)
    env.__dict__["_start_draw"] = StartDraw(env.rng.key, env._env_index, env.episodes)
    try:
        with pytest.raises(ValueError, match="first dim of the shape must be n=3, got shape \\(2,\\)"):
            env.uniform(0.0, 1.0, 2)
    finally:
        env.__dict__["_start_draw"] = None


def test_episodes_setter_checks_its_input():
    env = make_env("pendulum", num_envs=3, seed=0)
    with pytest.raises(ValueError, match="episodes must be 3 non-negative integers"):
        env.episodes = torch.tensor([1, 2])
    with pytest.raises(ValueError, match="episodes must be 3 non-negative integers"):
        env.episodes = torch.tensor([1, -2, 0])


def test_env_rng_state_carries_the_streams():
    """Checkpoints save ``env.rng.get_state()``: restored on an env built with another seed, it
    continues the same start states (and a plain generator state leaves the streams alone)."""
    env, other = make_env("CartPole-v1", num_envs=4, seed=1), make_env("CartPole-v1", num_envs=4, seed=2)
    env.reset()
    td = partial_reset(env, env.reset(), [2])
    state = env.rng.get_state()
    expected = [partial_reset(env, td, [0, 2])["observation"] for _ in range(2)]
    other.rng.set_state(state)
    assert torch.equal(other.episodes, torch.tensor([2, 2, 3, 2]))
    got = [partial_reset(other, td, [0, 2])["observation"] for _ in range(2)]
    assert all(a.equal(b) for a, b in zip(got, expected))
    plain = torch.Generator().manual_seed(0).get_state()
    other.rng.set_state(plain)
    assert torch.equal(other.rng.get_state()[: plain.numel()], plain)
    assert torch.equal(other.episodes, torch.tensor([4, 2, 5, 2]))


def test_env_rng_state_of_a_cuda_generator_loads_on_the_cpu():
    """A CUDA generator's state (16 bytes: Philox seed and offset) cannot be a CPU generator's
    (Mersenne Twister, 5056 bytes): a run resumed on another device seeds the generator from it,
    the same way every time, warns, and continues the start-state streams exactly."""
    env, other = make_env("CartPole-v1", num_envs=4, seed=1), make_env("CartPole-v1", num_envs=4, seed=2)
    td = partial_reset(env, env.reset(), [2])
    state = env.rng.get_state()
    own = env.rng.get_state().numel() - 8 * (4 + 2)
    philox = torch.arange(16, dtype=torch.uint8)  # what torch.cuda's generator.get_state() returns
    cuda_state = torch.cat([philox, state[own:]])
    expected = partial_reset(env, td, [0, 2])["observation"]
    draws = []
    for _ in range(2):
        with pytest.warns(RuntimeWarning, match="a cuda generator's \\(16 bytes\\).*streams continue exactly"):
            other.rng.set_state(cuda_state)
        assert torch.equal(other.episodes, torch.tensor([1, 1, 2, 1]))
        draws.append(torch.rand(3, generator=other.rng))
    assert torch.equal(draws[0], draws[1])
    assert torch.equal(partial_reset(other, td, [0, 2])["observation"], expected)
    with pytest.raises(ValueError, match="neither a cpu generator's .* nor one saved on the other kind of device"):
        other.rng.set_state(make_env("CartPole-v1", num_envs=3, seed=2).rng.get_state())  # another num_envs


def test_a_pickled_or_copied_env_continues_the_same_start_states():
    """ParallelEnv workers and deepcopies get the streams too (a plain torch.Generator would not)."""
    import copy
    import pickle

    env = make_env("pendulum", num_envs=3, seed=3)
    env.reset()
    a, b = copy.deepcopy(env), pickle.loads(pickle.dumps(env))
    assert torch.equal(a.episodes, env.episodes) and torch.equal(b.episodes, env.episodes)
    expected = env.reset()["observation"]
    assert torch.equal(a.reset()["observation"], expected) and torch.equal(b.reset()["observation"], expected)
