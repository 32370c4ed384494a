"""``compile_physics`` against eager: cold compile time, steady-state throughput and the
difference of the values and the aten ops per env step, per task and batch size, in two modes.

* ``rollout``: ``env.rollout(steps)`` without gradient, random actions (torch's generator seeded
  the same for both paths), ``compile_physics(env, steps_per_chunk=chunk)``;
* ``bptt``: a BPTT window: ``env.rollout(window, policy)`` from fixed start states with a
  64-64 tanh MLP policy (deterministic), then ``(-reward.mean()).backward()``; the compiled
  path compiles the forward and (AOTAutograd) the backward.

Every (task, N, mode) runs in a fresh process with an empty inductor cache (a temporary
``TORCHINDUCTOR_CACHE_DIR``), so that its compile time is cold. ``compile s``: the first compiled
call (a rollout, or a window's forward and backward) minus a steady-state one: tracing and
compiling; ``compile_report`` gives the first call of each compiled function (``first calls``).
Throughput: eager and compiled timed interleaved (see ``_common``), env-steps/s from CPU time,
the ratio is the median over rounds. ``max abs diff``: between the eager and the compiled
rollout's observations and rewards from the same start and actions, after the first env step and
over the whole rollout (and, for ``bptt``, of the policy's gradient relative to its largest
element). Beside it, ``eager at start x (1 +- 6e-8)``: the same gradient difference between eager
windows whose start states differ by float32's rounding (every float under ``"state"`` times
``1 + 6e-8 z``, 3 draws, the largest): how much rounding alone moves this window's gradient.
``aten ops per env step``: the profiler's count over a run of ``ops_steps`` env steps from the
same start (its backward included for ``bptt``) divided by them, the CPU proxy of the kernels a GPU would launch: fused
kernels replace most of eager's. ``dtype=float64`` runs both paths in float64, where the compiled math must equal eager's to
rounding (1e-10), however sensitive the window. Fused kernels round differently, and the contact tasks amplify rounding: on
HalfCheetah-v5 eager float32 and float64 rollouts from one start with the same random actions
are themselves 0.8 apart (max over 1024 envs; median 6e-6) after 32 steps. Articulated tasks (the MuJoCo ones) compile
one physics step, reused at every step; the others a ``chunk``-step chunk.

    python benchmarks/compile_physics.py                                   # HalfCheetah-v5, N=1024
    python benchmarks/compile_physics.py tasks=[Pendulum-v1] sizes=[64] modes=[bptt] data=none
    python benchmarks/compile_physics.py quick=true                        # smoke run
    python benchmarks/compile_physics.py from_results=[f32.json,f64.json]  # one data file from earlier runs' out=
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torchrl_diffenvs import checks  # noqa: E402
from torchrl_diffenvs.checks import checked, parse_cli  # noqa: E402

MODES = ("rollout", "bptt")


@dataclass(frozen=True)
class CompilePhysicsSettings(C.BenchmarkSettings):
    tasks: list[str] | None = None  # default [HalfCheetah-v5] (quick: [Hopper-v5])
    sizes: list[int] | None = None  # batch sizes N (default [1024]; quick: [4])
    modes: list[str] | None = None  # rollout, bptt (default both)
    steps: int | None = None  # rollout length (default 32; quick: 8)
    window: int | None = None  # BPTT window length (default 16; quick: 8)
    chunk: int = checked(8, checks.positive_int)  # steps_per_chunk
    # env steps of the run whose aten ops are counted (default: one chunk; a multiple of it, since steps
    # beyond whole chunks run eagerly). Not the whole run: the profiler keeps every op it records, about
    # 3 KB each, which with a 16-step window of the Ant and its backward at N=1024 outgrew 24 GiB
    ops_steps: int | None = None
    dtype: str = checked("float32", checks.one_of(("float32", "float64")))  # of the envs and the policy
    timeout: int = checked(900, checks.positive_int)  # seconds per (task, N, mode) process
    worker: str | None = None  # internal: "task,N,mode" measured in this process
    # the raw results (out=) of earlier runs, e.g. float32 and float64: write one data file from their rows
    from_results: list[str] | None = None

    @classmethod
    def relation_problems(cls, values, where=""):
        ops, chunk = values["ops_steps"], values["chunk"]
        if ops is not None and not (checks.is_int(ops) and ops >= chunk and ops % chunk == 0):
            return [f"{where}ops_steps={ops!r}: expected a multiple of chunk={chunk} (steps beyond whole "
                    "chunks run eagerly, so their ops would be counted as the compiled path's), or null for one chunk"]
        return []


def measure(task: str, n: int, mode: str, args) -> dict:
    """One (task, N, mode) in this process: compile time, interleaved timings, differences."""
    import torch

    from torchrl_diffenvs import compile_physics, make_env
    from torchrl_diffenvs.envs.rollout import compile_report

    quick = args.quick
    steps = args.steps or (8 if quick else 32)
    window = args.window or (8 if quick else 16)
    ops_steps = args.ops_steps or args.chunk
    dtype = getattr(torch, args.dtype)
    envs = {name: make_env(task, num_envs=n, seed=0, dtype=dtype) for name in ("eager", "compiled")}
    compile_physics(envs["compiled"], steps_per_chunk=args.chunk)
    start = envs["eager"].reset()
    net, policy = C.tanh_mlp_policy(envs["eager"], dtype)

    def runner(name: str, start=start, length: int | None = None):
        """The timed run of ``name``'s env and its env steps (the rollout's or window's, or ``length``)."""
        env = envs[name]
        length = length or (steps if mode == "rollout" else window)
        if mode == "rollout":
            def run():
                torch.manual_seed(1)
                with torch.no_grad():
                    return env.rollout(length, auto_reset=False, tensordict=start.clone())
            return run, length

        def run():
            net.zero_grad(set_to_none=True)
            out = env.rollout(length, policy, auto_reset=False, tensordict=start.clone())
            (-out["next", "reward"].mean()).backward()
            return out.detach(), [p.grad.clone() for p in net.parameters()]
        return run, length

    runs = {name: runner(name) for name in envs}
    length = runs["eager"][1]
    eager_out = runs["eager"][0]()
    first = time.perf_counter()
    compiled_out = runs["compiled"][0]()
    first = time.perf_counter() - first
    steady = time.perf_counter()
    runs["compiled"][0]()
    steady = time.perf_counter() - steady
    rounds = args.repeats or (2 if quick else 5)
    timings = C.interleaved({name: run for name, (run, _) in runs.items()}, rounds, warmup=0)
    cpu = {name: timings[name]["cpu"] for name in runs}
    rate = {name: length * n / C.spread(cpu[name])["median"] for name in runs}
    grad_diff = rounding_grad_diff = None
    if mode == "bptt":
        (eager_out, eager_grads), (compiled_out, compiled_grads) = eager_out, compiled_out
        scale_g = max(float(g.abs().max()) for g in eager_grads)

        def grad_diff_to_eager(grads):
            return max(float((a - b).abs().max()) for a, b in zip(grads, eager_grads)) / scale_g
        grad_diff = grad_diff_to_eager(compiled_grads)
        rounding_grad_diff = max(grad_diff_to_eager(runner("eager", perturbed_start(start, draw))[0]()[1])
                                 for draw in range(3))
    diffs = [(compiled_out["next", key] - eager_out["next", key]).abs() for key in ("observation", "reward")]
    diff = max(float(d.max()) for d in diffs)
    first_diff = max(float(d[:, 0].max()) for d in diffs)  # [N, T, ...]: after the first env step
    report = compile_report(envs["compiled"])
    ops = {name: C.aten_ops(runner(name, length=ops_steps)[0]) / ops_steps for name in runs}
    return {"task": task, "N": n, "mode": mode, "length": length, "eager_steps_per_s": rate["eager"],
            "compiled_steps_per_s": rate["compiled"], "ratio": C.median_ratio(cpu["eager"], cpu["compiled"]),
            "first_call_s": first, "steady_call_s": steady, "compile_s": first - steady,
            "first_calls": report["first_call_seconds"], "fallback_reason": report["fallback_reason"],
            "granularity": report["granularity"],
            "max_abs_diff": diff, "max_abs_diff_first_step": first_diff, "grad_rel_diff": grad_diff,
            "grad_rel_diff_rounding": rounding_grad_diff, "dtype": args.dtype, "rounds": rounds,
            "aten_ops_per_env_step": ops, "ops_steps": ops_steps,
            "cpu_s": {name: C.spread(cpu[name]) for name in cpu}}


def perturbed_start(start, draw: int):
    """``start`` with every float under ``"state"`` times ``1 + 6e-8 z`` (float32's rounding), z ~ N(0, 1)."""
    import torch

    generator = torch.Generator().manual_seed(draw)
    out = start.clone()
    for key, value in start.get("state").items(include_nested=True, leaves_only=True):
        if value.is_floating_point():
            noise = torch.randn(value.shape, generator=generator, dtype=value.dtype)
            out.set(("state", *((key,) if isinstance(key, str) else key)), value * (1 + 6e-8 * noise))
    return out


def run_worker(task: str, n: int, mode: str, argv: list[str], timeout: int) -> dict:
    """``measure`` in a fresh process with an empty inductor cache."""
    with tempfile.TemporaryDirectory(prefix="inductor-compile-physics-") as cache:
        env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": cache}
        command = [sys.executable, __file__, *argv, f"worker={task},{n},{mode}"]
        started = time.perf_counter()
        try:
            done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return {"task": task, "N": n, "mode": mode, "error": f"still compiling or running after {timeout} s"}
        for line in done.stdout.splitlines():
            if line.startswith("RESULT "):
                result = json.loads(line[len("RESULT "):])
                result["process_s"] = time.perf_counter() - started
                return result
        tail = " ".join((done.stderr or done.stdout).strip().splitlines()[-3:])
        return {"task": task, "N": n, "mode": mode, "error": f"exit {done.returncode}: {tail[-300:]}"}


def docs_tables(results: list[dict]) -> dict:
    rows = []
    for r in results:
        dtype = r.get("dtype", "float32")
        if "error" in r:
            rows.append([r["task"], r["N"], r["mode"], dtype, "-", "-", "-", "-", "-", r["error"], "-", "-"])
            continue
        diff = f"{r['max_abs_diff_first_step']:.2g} / {r['max_abs_diff']:.2g}"
        grads = "-"
        if r["grad_rel_diff"] is not None:
            grads = f"{r['grad_rel_diff']:.2g}"
            if r.get("grad_rel_diff_rounding") is not None:
                grads += f" / {r['grad_rel_diff_rounding']:.2g}"
        ops = r.get("aten_ops_per_env_step")
        ops = f"{ops['eager']:.0f} / {ops['compiled']:.0f}" if ops else "-"
        rows.append([r["task"], r["N"], {"rollout": "no-grad rollout", "bptt": "BPTT window"}[r["mode"]], dtype,
                     C.fmt_rate(r["eager_steps_per_s"]), C.fmt_rate(r["compiled_steps_per_s"]),
                     C.fmt_ratio(r["ratio"]), f"{r['compile_s']:.0f}", r["granularity"], diff, grads, ops])
    return {"compile_physics": C.data_table(
        "compile_physics against eager: env-steps/s from CPU time, cold compile seconds, max abs difference",
        ["task", "N", "mode", "dtype", "eager", "compiled", "compiled/eager", "compile s", "compiled unit",
         "max abs diff (step 1 / all)", "policy grad vs eager, rel: compiled / eager at start x (1 +- 6e-8)",
         "aten ops per env step (eager / compiled)"],
        rows)}


def render_results(args) -> dict:
    """The data file of earlier runs' raw results (``out=`` of each), their rows in the given order."""
    raws = [json.loads(Path(path).read_text()) for path in args.from_results]
    results = [row for raw in raws for row in raw["results"]]
    C.write_data(args, "compile_physics", docs_tables(results), measured=C.measured_from_raw(raws, "compile_physics.py"))
    return {"benchmark": "compile_physics", "results": results}


def main(argv=None) -> dict | None:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_cli(CompilePhysicsSettings, argv, __doc__)
    C.setup_threads(args.threads)
    if args.from_results:
        return render_results(args)
    if args.worker is not None:
        task, n, mode = args.worker.split(",")
        print("RESULT " + json.dumps(measure(task, int(n), mode, args)), flush=True)
        return None
    tasks = args.tasks or (["Hopper-v5"] if args.quick else ["HalfCheetah-v5"])
    sizes = args.sizes or ([4] if args.quick else [1024])
    modes = args.modes or list(MODES)
    if set(modes) - set(MODES):
        raise SystemExit(f"modes={modes}: valid {list(MODES)}")
    info = C.versions()
    info["machine"] = C.machine_name()
    C.print_header("compile_physics against eager (cold compile, CPU-time rates)", info)
    results = []
    for task in tasks:
        for n in sizes:
            for mode in modes:
                result = run_worker(task, n, mode, argv, args.timeout)
                results.append(result)
                print(json.dumps({k: v for k, v in result.items() if k != "cpu_s"}), flush=True)
    tables = docs_tables(results)
    table = tables["compile_physics"]
    C.print_table(table["columns"], table["rows"])
    C.write_data(args, "compile_physics", tables)
    payload = {"benchmark": "compile_physics", "date": C.today(), "info": info, "results": results}
    C.write_json("compile_physics" + ("_quick" if args.quick else ""), payload, args.out)
    return payload


if __name__ == "__main__":
    main()
