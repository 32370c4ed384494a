"""The MuJoCo-model tasks: env-steps/s of ours against gymnasium and MuJoCo's C step, one process.

For each task and N in {1, 64, 1024, 4096}, timed interleaved (see benchmarks/_common.py):

* ``ours``: ``env.rollout(T, break_when_any_done=False)`` under ``torch.no_grad`` (random
  actions, auto-resets included);
* ``ours fwd+bwd``: a BPTT window, ``env.rollout(H, policy)`` with a 64-64 tanh MLP policy and
  the backward of its summed reward (H = 8): what a gradient-based learner pays per env-step, at
  N <= ``window_max_n`` (default 1024: the activations saved for backward grow with N);
* ``gymnasium``: one ``gym.make(task)`` env stepped with sampled actions (reset when done);
* ``gymnasium SyncVectorEnv``: ``SyncVectorEnv`` of N envs (N <= 64: beyond that it is N times
  the single env plus bookkeeping, and a batch step takes seconds);
* ``mj_step (C)``: ``mujoco.mj_step(model, data, nstep=frame_skip * K)`` on one ``MjData``:
  MuJoCo's C physics with no Python per step, the speed limit of one env on one core;
* ``MJX (CPU)``: MuJoCo XLA (``mujoco.mjx``, JAX on the CPU, XLA's Eigen kernels on one thread
  with ``threads=1``; rates from CPU time, all threads counted): ``jit(scan(vmap(env step)))``
  over ``min(T, 2048 / N)`` steps (at least one) of N envs, an env step being ``frame_skip``
  ``mjx.step`` calls with the action held (no resets: MJX has none), compiled before timing (the
  compile time is in the JSON), at N <= 64 (at N = 1024 jaxlib's batched LAPACK calls in MJX's
  constraint solve deadlocked on this CPU, beside torch). Needs the ``bench`` extra
  (``mujoco-mjx``, ``jax``); without it the column is ``-``.

The gymnasium and MuJoCo rows do not depend on N; they run in every row so that each ratio is
taken within a round. Unit: env-steps/s (a batched step of N envs counts N) from CPU time.
The target of issue 9: ``ours`` at N = 1024 above one gymnasium env.

    OMP_NUM_THREADS=1 python benchmarks/mujoco_throughput.py            # several minutes
    python benchmarks/mujoco_throughput.py quick=true                     # smoke run, seconds
    python benchmarks/mujoco_throughput.py out=raw.json resume=raw.json   # go on where a run stopped

Needs ``pip install "torchrl_diffenvs[mujoco]"`` (gymnasium's MuJoCo envs).
"""
from __future__ import annotations

import json
import os
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torchrl_diffenvs.checks import checked, is_int, nonnegative_int, parse_cli  # noqa: E402

TASKS = ("HalfCheetah-v5", "Hopper-v5", "InvertedDoublePendulum-v5", "Ant-v5")
WINDOW = 8  # H of the forward+backward window
MJX_ENV_STEPS = 2048  # env steps per timed MJX call, at most (T shrinks with N; at least one step)
MJX_MAX_N = 64  # above it MJX is not timed: its batched LAPACK calls deadlocked on the CPU at N = 1024
# above it the BPTT window is not timed by default: the activations it saves for backward grow with N
# (on MuJoCo's contact the Ant's 8-step window at N = 4096 and the Humanoid's at N = 1024 each
# outgrew 20 GiB of memory)
WINDOW_MAX_N = 1024


def make_policy(env):
    import torch
    from tensordict.nn import TensorDictModule

    obs_dim = env.observation_spec["observation"].shape[-1]
    net = torch.nn.Sequential(
        torch.nn.Linear(obs_dim, 64), torch.nn.Tanh(), torch.nn.Linear(64, 64), torch.nn.Tanh(),
        torch.nn.Linear(64, env.action_dim), torch.nn.Tanh(),
    )
    return TensorDictModule(net, ["observation"], ["action"])


def candidates(task: str, n: int, steps: int, gym_steps: int, sync_max: int,
               mjx_max_n: int = MJX_MAX_N, window_max_n: int = WINDOW_MAX_N) -> tuple[dict, dict, dict]:
    """``(name -> fn, name -> env-steps per call, notes)`` for one row (notes: MJX's compile time,
    or why it did not run, and why the window was not timed)."""
    import gymnasium as gym
    import mujoco
    import torch

    from torchrl_diffenvs import make_env

    env = make_env(task, num_envs=n, seed=0)
    grad_env = make_env(task, num_envs=n, seed=1)
    policy = make_policy(grad_env)

    def ours():
        with torch.no_grad():
            return env.rollout(steps, break_when_any_done=False)

    def ours_fwd_bwd():
        td = grad_env.rollout(WINDOW, policy, break_when_any_done=False)
        (-td["next", "reward"].sum()).backward()
        policy.zero_grad(set_to_none=True)

    single = gym.make(task)
    single.reset(seed=0)

    def gymnasium_single():
        for _ in range(gym_steps):
            _, _, terminated, truncated, _ = single.step(single.action_space.sample())
            if terminated or truncated:
                single.reset()

    model, data = single.unwrapped.model, mujoco.MjData(single.unwrapped.model)
    mujoco.mj_resetData(model, data)
    frame_skip = env.frame_skip

    def mj_step_c():
        mujoco.mj_resetData(model, data)  # the same start every call: no drift into NaNs
        mujoco.mj_step(model, data, nstep=frame_skip * gym_steps)

    fns = {"ours": ours, "ours fwd+bwd": ours_fwd_bwd, "gymnasium": gymnasium_single, "mj_step (C)": mj_step_c}
    counts = {"ours": n * steps, "ours fwd+bwd": n * WINDOW, "gymnasium": gym_steps, "mj_step (C)": gym_steps}
    notes = {}
    if n > window_max_n:
        del fns["ours fwd+bwd"], counts["ours fwd+bwd"]
        notes["window"] = f"not timed: N > window_max_n={window_max_n}"
    mjx_steps = max(1, min(steps, MJX_ENV_STEPS // n))  # MJX on the CPU runs a few hundred env-steps/s
    if n <= min(mjx_max_n, MJX_MAX_N):
        mjx = mjx_rollout(model, frame_skip, n, mjx_steps)
    elif mjx_max_n < MJX_MAX_N:
        mjx = f"not timed: N > mjx_max_n={mjx_max_n}"
    else:
        mjx = f"N > {MJX_MAX_N}: jaxlib's batched LAPACK calls (MJX's constraint solve) hung on the CPU at N = 1024"
    if isinstance(mjx, tuple):
        fns["MJX (CPU)"], counts["MJX (CPU)"] = mjx[0], n * mjx_steps
    if n <= sync_max:
        vec = gym.vector.SyncVectorEnv([lambda: gym.make(task) for _ in range(n)], autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
        vec.reset(seed=0)
        vec_steps = max(1, gym_steps // n)

        def gymnasium_sync():
            for _ in range(vec_steps):
                vec.step(vec.action_space.sample())

        fns["gymnasium SyncVectorEnv"] = gymnasium_sync
        counts["gymnasium SyncVectorEnv"] = n * vec_steps
    notes.update({"mjx_compile_s": mjx[1]} if isinstance(mjx, tuple) else {"mjx": mjx})
    return fns, counts, notes


def mjx_rollout(model, frame_skip: int, n: int, steps: int):
    """MJX's compiled rollout of ``steps`` env steps of ``n`` envs from qpos0 (slightly perturbed),
    random actions in the control range: ``(run, compile_s)``, or a string saying why MJX cannot run."""
    try:
        import jax
        from mujoco import mjx
    except ImportError as error:
        return f"mujoco-mjx / jax not installed ({error}): pip install 'torchrl_diffenvs[bench]'"
    import time

    try:
        mx = mjx.put_model(model)
    except NotImplementedError as error:  # a geom pair or option MJX does not support
        return f"MJX cannot run this model: {error}"
    start = mjx.make_data(mx)
    keys = jax.random.split(jax.random.PRNGKey(0), n)
    batch = jax.vmap(lambda k: start.replace(qpos=start.qpos + 0.01 * jax.random.normal(k, start.qpos.shape)))(keys)
    low, high = model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1]
    actions = jax.random.uniform(jax.random.PRNGKey(1), (steps, n, model.nu), minval=low, maxval=high)

    def env_step(data, action):
        data = data.replace(ctrl=action)
        data, _ = jax.lax.scan(lambda d, _: (mjx.step(mx, d), None), data, None, length=frame_skip)
        return data

    @jax.jit
    def rollout(data, actions):
        data, _ = jax.lax.scan(lambda d, a: (jax.vmap(env_step)(d, a), None), data, actions)
        return data.qpos

    began = time.perf_counter()
    rollout(batch, actions).block_until_ready()  # compile
    compile_s = time.perf_counter() - began

    def run():  # the envs' final qpos
        return rollout(batch, actions).block_until_ready()
    run.start_qpos = batch.qpos  # where the timed rollouts start (what a test compares against)
    return run, compile_s


@dataclass(frozen=True)
class MuJoCoThroughputSettings(C.BenchmarkSettings):
    tasks: list[str] = field(default_factory=lambda: list(TASKS))
    sizes: list[int] | None = None  # N values (default 1 64 1024 4096)
    # MJX is timed up to this N, at most MJX_MAX_N (each N compiles for a minute or more; 0: never)
    mjx_max_n: int = checked(MJX_MAX_N, lambda v: None if is_int(v) and 0 <= v <= MJX_MAX_N
                             else f"expected an integer in [0, {MJX_MAX_N}]")
    # the BPTT window (``ours fwd+bwd``) is timed up to this N (its memory grows with N; 0: never)
    window_max_n: int = checked(WINDOW_MAX_N, nonnegative_int)
    # the raw JSON (``out=``) of an earlier run with the same settings that stopped part-way: its
    # (task, N) rows are kept and not measured again
    resume: str | None = None


def _rate(cands: dict, name: str):
    return cands[name]["env_steps_per_s_cpu"]["median"] if name in cands else None


def _row(result: dict) -> list:
    """The table's row of one (task, N) result."""
    cands, ratios = result["candidates"], result["ratios_cpu"]
    return [result["task"], result["N"], *(C.fmt_rate(_rate(cands, name)) for name in (
                "ours", "ours fwd+bwd", "gymnasium", "gymnasium SyncVectorEnv", "mj_step (C)", "MJX (CPU)")),
            C.fmt_ratio(ratios["ours / gymnasium"]),
            C.fmt_ratio(ratios["ours / MJX (CPU)"]) if "MJX (CPU)" in cands else "-"]


def main(argv=None) -> dict:
    args = parse_cli(MuJoCoThroughputSettings, argv, __doc__)
    C.setup_threads(args.threads)
    if args.threads == 1:  # before jax is imported: XLA's Eigen kernels on one thread too (its intra-op
        # pool stays: limited to one thread, jaxlib's batched LAPACK calls deadlock; rates are CPU time)
        os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false")
    warnings.filterwarnings("ignore")
    sizes = args.sizes or ([1, 4] if args.quick else [1, 64, 1024, 4096])
    rounds = args.repeats or (2 if args.quick else 3)
    gym_steps = 20 if args.quick else 2000
    info = C.versions()
    C.print_header("MuJoCo-model tasks: env-steps/s (CPU time)", info)
    results, rows = [], []
    earlier = {}
    if args.resume:
        if not Path(args.resume).is_file():
            raise SystemExit(f"resume={args.resume!r}: no such file; expected the raw JSON an earlier run wrote "
                             "with out=")
        earlier = {(r["task"], r["N"]): r for r in json.loads(Path(args.resume).read_text())["results"]}
    for task in args.tasks:
        for n in sizes:
            if (task, n) in earlier:
                results.append(earlier[(task, n)])
                rows.append(_row(earlier[(task, n)]))
                print(f"# {task} N={n}: kept from {args.resume}", flush=True)
                continue
            steps = 2 if args.quick else max(2, min(50, 20000 // n))
            fns, counts, notes = candidates(task, n, steps, gym_steps, sync_max=4 if args.quick else 64,
                                            mjx_max_n=args.mjx_max_n, window_max_n=args.window_max_n)
            times = C.interleaved(fns, rounds)
            cands = {}
            for name, t in times.items():
                cands[name] = {
                    "env_steps_per_call": counts[name],
                    "env_steps_per_s_cpu": C.spread([counts[name] / c for c in t["cpu"]]),
                    "env_steps_per_s_wall": C.spread([counts[name] / w for w in t["wall"]]),
                }
            # ratio of rates within a round = inverse ratio of per-env-step times
            per_step = {name: [c / counts[name] for c in t["cpu"]] for name, t in times.items()}
            ratios = {f"ours / {name}": C.median_ratio(per_step[name], per_step["ours"])
                      for name in fns if name != "ours"}
            results.append({"task": task, "N": n, "T": steps, "H": WINDOW, "candidates": cands, "ratios_cpu": ratios,
                            **notes})
            rows.append(_row(results[-1]))
            print(f"# {task} N={n}: " + ", ".join(f"{k} {C.fmt_rate(_rate(cands, k))}" for k in cands), flush=True)
            # the raw results so far, so that a run stopped part-way (memory, time) keeps its rows
            C.write_json("mujoco_throughput", {"benchmark": "mujoco_throughput", "info": info, "results": results,
                                               "complete": False}, args.out)
    table = C.print_table(["task", "N", "ours", "ours fwd+bwd", "gymnasium", "gym SyncVectorEnv", "mj_step (C)",
                           "MJX (CPU)", "ours / gymnasium", "ours / MJX"], rows)
    payload = {"benchmark": "mujoco_throughput", "info": info, "results": results, "table": table, "complete": True}
    C.write_json("mujoco_throughput", payload, args.out)
    C.write_data(args, "mujoco_throughput", {"rates": C.data_table(
        "MuJoCo tasks: env-steps/s, one thread, from CPU time",
        ["task", "N", "ours", "ours fwd+bwd", "gymnasium, 1 env", "SyncVectorEnv", "mj_step (C)", "MJX (CPU)",
         "ours / gymnasium", "ours / MJX"],
        rows)})
    return payload


if __name__ == "__main__":
    main()
