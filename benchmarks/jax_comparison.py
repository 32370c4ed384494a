"""Side by side with JAX, in one process, one thread: our envs against gymnax's jit(vmap + scan)
on the tasks both have, a raw JAX scan of the same pendulum physics, and BPTT gradients (JAX's
``value_and_grad`` over ``scan`` against our ``env.rollout`` + ``backward``) with the same policy.

Forward, per shared task, ``N`` envs for ``T`` steps with uniformly random actions:

* ``ours``: ``env.rollout(T)`` under ``no_grad`` (the lean rollout path, outputs stacked);
* ``ours compiled`` (``compile=true``): the same after ``compile_physics(env)``;
* ``gymnax``: ``jit(scan(vmap(env.step)))`` of gymnax's env (auto-reset inside its step), the
  random actions drawn inside the jitted function, rewards stacked ``[T, N]``;
* for Pendulum-v1 only, ``raw JAX``: the same physics written as a plain ``jnp`` scan (no env
  machinery), against ``raw torch``: the same loop in plain torch.

BPTT (Pendulum-v1): a window of ``H`` steps from fixed states with a 64-64 tanh MLP policy, loss
``-mean(reward)``, gradient w.r.t. the policy's parameters:

* ``ours fwd+bwd``: ``env.rollout(H, policy)`` then ``backward`` (our BPTT window);
* ``ours compiled`` (``compile=true``): the same after ``compile_physics(env)`` (8-step chunks of
  policy + physics, forward and backward compiled);
* ``JAX value_and_grad``: ``jit(value_and_grad(loss))`` with the loss a ``scan`` over gymnax's
  Pendulum-v1 ``step_env`` and the same MLP in ``jnp``.

Shared tasks (ours <-> gymnax): Pendulum-v1, CartPole-v1, MountainCarContinuous-v0 (Gymnasium's
dynamics in both), reacher <-> Reacher-misc and swimmer <-> Swimmer-misc (Ivy Gym's tasks).
JAX is told to use one thread (``XLA_FLAGS``, set before it is imported); JIT compilation is
excluded from the times (each function runs once before timing). Unit: env-steps/s from CPU time
(benchmarks/_common.py). Needs the ``bench`` extra (``pip install -e ".[bench]"``: jax, gymnax);
without it the JAX columns are skipped with a note.

    python benchmarks/jax_comparison.py quick=true                  # smoke run, seconds
    OMP_NUM_THREADS=1 python benchmarks/jax_comparison.py sizes=[1024] steps=200
"""
from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

# one thread for XLA too; must be set before jax is imported anywhere in this process
os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torchrl_diffenvs import checks  # noqa: E402
from torchrl_diffenvs.checks import checked, parse_cli  # noqa: E402

SHARED = {  # ours -> gymnax
    "Pendulum-v1": "Pendulum-v1",
    "CartPole-v1": "CartPole-v1",
    "MountainCarContinuous-v0": "MountainCarContinuous-v0",
    "reacher": "Reacher-misc",
    "swimmer": "Swimmer-misc",
}


@dataclass(frozen=True)
class JaxComparisonSettings(C.BenchmarkSettings):
    tasks: list[str] = checked(list(SHARED), checks.each(checks.one_of(list(SHARED))))
    sizes: list[int] | None = None  # N (default 1024; quick: 8)
    steps: int | None = None  # T of the forward rollouts (default 200; quick: 8)
    horizon: int | None = None  # H of the BPTT window (default 32; quick: 4)
    hidden: list[int] = field(default_factory=lambda: [64, 64])  # the policy's hidden layers
    compile: bool = checked(False, checks.boolean)  # also time ours after compile_physics
    # where our envs run: cpu | cuda | cuda:<k> (gymnasium and JAX stay on the CPU). On CUDA the timings
    # synchronise the device; read the wall-clock rates (JSON, *_wall), not the CPU-time ones
    device: str = "cpu"


def jax_available() -> str | None:
    """``None`` when jax and gymnax import, else why not."""
    import importlib

    try:
        for module in ("jax", "gymnax"):
            importlib.import_module(module)
    except ImportError as err:
        return f"{err.name or err} is not installed (pip install -e '.[bench]')"
    return None


# ---------------------------------------------------------------------- ours (torch)
def ours_forward(task: str, n: int, t: int, compiled: bool = False, device: str = "cpu"):
    import torch

    from torchrl_diffenvs import compile_physics, make_env

    env = make_env(task, num_envs=n, seed=0, device=device)
    if compiled:
        compile_physics(env)

    def run():
        with torch.no_grad():
            return env.rollout(t, break_when_any_done=False)["next", "reward"]

    return run


def torch_mlp(in_dim: int, out_dim: int, hidden, dtype):
    import torch
    from torch import nn

    layers, width = [], in_dim
    for h in hidden:
        layers += [nn.Linear(width, h, dtype=dtype), nn.Tanh()]
        width = h
    layers += [nn.Linear(width, out_dim, dtype=dtype), nn.Tanh()]
    torch.manual_seed(0)
    return nn.Sequential(*layers)


def ours_bptt(n: int, h: int, hidden, compiled: bool = False, device: str = "cpu"):
    """Our BPTT window on Pendulum-v1: rollout with the policy, then backward."""
    from tensordict.nn import TensorDictModule

    from torchrl_diffenvs import compile_physics, make_env

    env = make_env("Pendulum-v1", num_envs=n, seed=0, device=device)
    if compiled:
        compile_physics(env)
    net = torch_mlp(env.observation_dim, env.action_dim, hidden, env.float_dtype).to(env.device)
    scale = float(env.action_spec.space.high.flatten()[0])
    policy = TensorDictModule(lambda obs: net(obs) * scale, in_keys=["observation"], out_keys=["action"])
    start = env.reset()

    def run():
        net.zero_grad(set_to_none=True)
        rollout = env.rollout(h, policy, tensordict=start.clone(), auto_reset=False)
        loss = -rollout["next", "reward"].mean()
        loss.backward()
        return loss.detach()

    return run


def raw_torch_pendulum(n: int, t: int):
    """Gymnasium's Pendulum-v1 physics as a plain torch loop (random torques), rewards stacked."""
    import torch

    g, m, length, dt, max_speed, max_torque = 10.0, 1.0, 1.0, 0.05, 8.0, 2.0
    gen = torch.Generator().manual_seed(0)
    th0 = torch.rand(n, generator=gen) * 2 * torch.pi - torch.pi
    thd0 = torch.rand(n, generator=gen) * 2 - 1

    def run():
        th, thd, rewards = th0, thd0, []
        for _ in range(t):
            u = torch.rand(n, generator=gen) * 2 * max_torque - max_torque
            norm = torch.remainder(th + torch.pi, 2 * torch.pi) - torch.pi
            rewards.append(-(norm**2 + 0.1 * thd**2 + 0.001 * u**2))
            thd = torch.clamp(thd + (3 * g / (2 * length) * torch.sin(th) + 3.0 / (m * length**2) * u) * dt,
                              -max_speed, max_speed)
            th = th + thd * dt
        return torch.stack(rewards)

    return run


# ---------------------------------------------------------------------- JAX
def gymnax_forward(gymnax_id: str, n: int, t: int):
    import gymnax
    import jax

    env, params = gymnax.make(gymnax_id)
    keys = jax.random.split(jax.random.PRNGKey(0), n)
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    space = env.action_space(params)

    @jax.jit
    def rollout(state, key):
        def one_step(carry, _):
            state, key = carry
            key, k_act, k_step = jax.random.split(key, 3)
            actions = jax.vmap(space.sample)(jax.random.split(k_act, n))
            out = jax.vmap(env.step, in_axes=(0, 0, 0, None))(jax.random.split(k_step, n), state, actions, params)
            state, reward = out[1], out[2]  # (obs, state, reward, done flags..., info)
            return (state, key), reward

        _, rewards = jax.lax.scan(one_step, (state, key), None, length=t)
        return rewards

    key = jax.random.PRNGKey(1)
    return lambda: rollout(state, key).block_until_ready()


def raw_jax_pendulum(n: int, t: int):
    import jax
    import jax.numpy as jnp

    g, m, length, dt, max_speed, max_torque = 10.0, 1.0, 1.0, 0.05, 8.0, 2.0
    k0, k1 = jax.random.split(jax.random.PRNGKey(0))
    th0 = jax.random.uniform(k0, (n,), minval=-jnp.pi, maxval=jnp.pi)
    thd0 = jax.random.uniform(k1, (n,), minval=-1.0, maxval=1.0)

    @jax.jit
    def rollout(th, thd, key):
        def one_step(carry, _):
            th, thd, key = carry
            key, k = jax.random.split(key)
            u = jax.random.uniform(k, (n,), minval=-max_torque, maxval=max_torque)
            norm = jnp.remainder(th + jnp.pi, 2 * jnp.pi) - jnp.pi
            reward = -(norm**2 + 0.1 * thd**2 + 0.001 * u**2)
            thd = jnp.clip(thd + (3 * g / (2 * length) * jnp.sin(th) + 3.0 / (m * length**2) * u) * dt,
                           -max_speed, max_speed)
            return (th + thd * dt, thd, key), reward

        _, rewards = jax.lax.scan(one_step, (th, thd, key), None, length=t)
        return rewards

    key = jax.random.PRNGKey(2)
    return lambda: rollout(th0, thd0, key).block_until_ready()


def jax_bptt(n: int, h: int, hidden):
    """``jit(value_and_grad)`` of ``-mean(reward)`` over an ``H``-step scan of gymnax's Pendulum-v1."""
    import gymnax
    import jax
    import jax.numpy as jnp

    env, params = gymnax.make("Pendulum-v1")
    keys = jax.random.split(jax.random.PRNGKey(0), n)
    obs0, state0 = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    sizes = [obs0.shape[-1], *hidden, 1]
    weights, key = [], jax.random.PRNGKey(3)
    for fan_in, fan_out in zip(sizes[:-1], sizes[1:]):
        key, k = jax.random.split(key)
        bound = 1.0 / fan_in**0.5  # torch.nn.Linear's initialisation range
        weights.append((jax.random.uniform(k, (fan_in, fan_out), minval=-bound, maxval=bound), jnp.zeros(fan_out)))

    def policy(weights, obs):
        x = obs
        for w, b in weights:
            x = jnp.tanh(x @ w + b)
        return x * params.max_torque

    def loss(weights):
        def one_step(carry, _):
            obs, state = carry
            action = policy(weights, obs)
            out = jax.vmap(env.step_env, in_axes=(None, 0, 0, None))(jax.random.PRNGKey(0), state, action, params)
            obs, state, reward = out[0], out[1], out[2]  # no auto-reset inside the window
            return (obs, state), reward

        _, rewards = jax.lax.scan(one_step, (obs0, state0), None, length=h)
        return -rewards.mean()

    grad_fn = jax.jit(jax.value_and_grad(loss))
    return lambda: jax.block_until_ready(grad_fn(weights))


# ---------------------------------------------------------------------- the benchmark
def main(argv=None) -> dict:
    args = parse_cli(JaxComparisonSettings, argv, __doc__)
    C.setup_threads(args.threads)
    device = C.setup_device(args.device)
    quick = args.quick
    sizes = args.sizes or ([8] if quick else [1024])
    t = args.steps or (8 if quick else 200)
    h = args.horizon or (4 if quick else 32)
    rounds = args.repeats or (2 if quick else 5)
    missing = jax_available()
    info = C.versions()
    info["device"] = device
    if missing is None:
        import gymnax
        import jax

        info.update(jax=jax.__version__, gymnax=getattr(gymnax, "__version__", "?"),
                    xla_flags=os.environ.get("XLA_FLAGS"))
    else:
        info["jax"] = f"skipped: {missing}"
        print(f"# JAX columns skipped: {missing}")
    C.print_header(f"side by side with JAX: env-steps/s (CPU time), T = {t}, BPTT H = {h}", info)

    results, rows = [], []
    for n in sizes:
        for task in args.tasks:
            fns = {"ours": ours_forward(task, n, t, device=device)}
            if args.compile:
                fns["ours compiled"] = ours_forward(task, n, t, compiled=True, device=device)
            if missing is None:
                fns["gymnax"] = gymnax_forward(SHARED[task], n, t)
            if task == "Pendulum-v1":
                fns["raw torch"] = raw_torch_pendulum(n, t)
                if missing is None:
                    fns["raw JAX"] = raw_jax_pendulum(n, t)
            results.append(summarise("forward", task, n, t, fns, rounds))
            rows.append(row(results[-1]))
        bptt = {"ours fwd+bwd": ours_bptt(n, h, args.hidden, device=device)}
        if args.compile:
            bptt["ours compiled"] = ours_bptt(n, h, args.hidden, compiled=True, device=device)
        if missing is None:
            bptt["JAX value_and_grad"] = jax_bptt(n, h, args.hidden)
        results.append(summarise("BPTT", "Pendulum-v1", n, h, bptt, rounds))
        rows.append(row(results[-1]))
    headers = ["kind", "task", "N", "T", "ours", "ours compiled", "gymnax / JAX", "raw torch", "raw JAX",
               "ours / gymnax or JAX", "compiled / gymnax or JAX", "compiled / ours"]
    table = C.print_table(headers, rows)
    payload = {"benchmark": "jax_comparison", "info": info, "results": results, "table": table,
               "jax_skipped": missing}
    C.write_json("jax_comparison" + ("_quick" if quick else ""), payload, args.out)
    C.write_data(args, "jax_comparison", {"comparison": C.data_table(
        "Side by side with JAX: env-steps/s from CPU time, one thread", headers, rows)}, device)
    return payload


def summarise(kind: str, task: str, n: int, t: int, fns: dict, rounds: int) -> dict:
    times = C.interleaved(fns, rounds)
    steps = n * t
    candidates = {name: {"env_steps_per_s_cpu": C.spread([steps / c for c in tm["cpu"]]),
                         "env_steps_per_s_wall": C.spread([steps / w for w in tm["wall"]])}
                  for name, tm in times.items()}
    reference = "gymnax" if "gymnax" in times else "JAX value_and_grad" if "JAX value_and_grad" in times else None
    ours = "ours" if "ours" in times else "ours fwd+bwd"
    ratio = None if reference is None else C.median_ratio(times[reference]["cpu"], times[ours]["cpu"])
    result = {"kind": kind, "task": task, "N": n, "T": t, "candidates": candidates, f"{ours} / {reference}": ratio}
    if "ours compiled" in times:
        result["ours compiled / ours"] = C.median_ratio(times[ours]["cpu"], times["ours compiled"]["cpu"])
        result["ours compiled / reference"] = (None if reference is None else
                                               C.median_ratio(times[reference]["cpu"], times["ours compiled"]["cpu"]))
    print(f"# {kind} {task} N={n}: " + ", ".join(
        f"{k} {C.fmt_rate(v['env_steps_per_s_cpu']['median'])}" for k, v in candidates.items()), flush=True)
    return result


def row(result: dict) -> list:
    c = result["candidates"]

    def rate(*names):
        for name in names:
            if name in c:
                return C.fmt_rate(c[name]["env_steps_per_s_cpu"]["median"])
        return "-"

    ratio = next((v for k, v in result.items() if " / " in k and not k.startswith("ours compiled")), None)
    return [result["kind"], result["task"], result["N"], result["T"], rate("ours", "ours fwd+bwd"),
            rate("ours compiled"), rate("gymnax", "JAX value_and_grad"), rate("raw torch"), rate("raw JAX"),
            C.fmt_ratio(ratio), C.fmt_ratio(result.get("ours compiled / reference")),
            C.fmt_ratio(result.get("ours compiled / ours"))]


if __name__ == "__main__":
    main()
