"""Throughput on a GPU, wall clock: env steps without gradient and BPTT windows with their
backward, per task and batch size, eager, compiled and compiled with CUDA graphs.

For each task and N (sizes up to 65536), timed on the device with ``torch.cuda.synchronize``
after every call (env-steps/s = N x steps / wall seconds, the median of ``repeats`` calls after
one warm-up call, which is also the compiling call):

* ``rollout``: ``env.rollout(steps, break_when_any_done=False)`` under ``torch.no_grad``, random
  actions, auto-resets included;
* ``bptt``: a ``window``-step ``env.rollout`` from fixed start states with a 64-64 tanh MLP
  policy (deterministic), then ``(-reward.mean()).backward()``;

in each of the modes ``eager``; ``compiled`` (``compile_physics(env, steps_per_chunk=8)``) and
``cudagraphs`` (the same with ``mode="reduce-overhead"``: inductor's CUDA graphs around each
compiled graph; rollouts only: ``compile_physics`` compiles windows with gradient without CUDA
graphs, so their cell is ``n/a``). A compiled mode's warm-up time (tracing, compiling, the first run) is reported
as ``first call s``. Two diagnostics per task, at the first size: the CUDA kernels launched by
one env step without gradient (``torch.profiler``) and the host-device synchronisations in it
(``torch.cuda.set_sync_debug_mode``): an eager GPU step that launches thousands of small kernels is
bound by their launch overhead, not by the GPU. With ``hotspots=K``, also the K source lines of the
library whose torch calls take the most device time in one env step (the docs' hotspot table).

A MuJoCo task can be named with options after colons: its contact model (``HalfCheetah-v5:smooth``;
default: the task's own, ``mujoco``) and ``recompute`` (``recompute_in_backward=True``: each env
step's physics runs again in the backward instead of keeping its intermediates), to measure them
side by side. A ``bptt`` cell also reports the bytes its graph saves for the backward per env step
(``saved KiB per env-step``: distinct storages through ``torch.autograd.graph.saved_tensors_hooks``
in the warm-up call; with ``recompute``, what the checkpoints keep is not counted: each env step's
inputs, which the rollout holds anyway).

``budget_s`` bounds the whole run: once it is spent the remaining cells are reported as
skipped; results are written after every cell, so a run stopped from outside keeps what it
measured. An out-of-memory cell is reported as such and the run goes on.

    python benchmarks/gpu_throughput.py                                     # device=cuda, every task
    python benchmarks/gpu_throughput.py tasks=[HalfCheetah-v5] sizes=[16384,65536] modes=[eager,cudagraphs]
    python benchmarks/gpu_throughput.py tasks=[HalfCheetah-v5,HalfCheetah-v5:smooth] sizes=[65536]  # both contact models
    python benchmarks/gpu_throughput.py quick=true device=cpu                # smoke run on the CPU
"""
from __future__ import annotations

import os
import statistics
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torchrl_diffenvs import checks  # noqa: E402
from torchrl_diffenvs.checks import checked, parse_cli  # noqa: E402

MODES = ("eager", "compiled", "cudagraphs")
# small algebra helpers: their calls count at the line that called them (which product, not which helper)
HELPER_MODULES = ("articulated/spatial.py",)
HOTSPOT_ROWS = 12  # per task in the docs table (the raw results keep all `hotspots=` asked)
NOT_APPLICABLE = "n/a: windows with gradient compile without CUDA graphs (the compiled column)"
KINDS = ("rollout", "bptt")
# The Ivy tasks, Gymnasium's classic control and the MuJoCo suite (the multi-agent envs roll out through
# EnvBase.rollout, which neither compile_physics nor this benchmark's lean rollout covers)
DEFAULT_TASKS = ("pendulum", "cartpole", "mountaincar", "reacher", "swimmer", "Pendulum-v1", "CartPole-v1",
                 "HalfCheetah-v5", "Hopper-v5", "Walker2d-v5", "Ant-v5", "Humanoid-v5", "Swimmer-v5",
                 "InvertedPendulum-v5", "Reacher-v5")


@dataclass(frozen=True)
class GPUThroughputSettings(C.BenchmarkSettings):
    tasks: list[str] | None = None  # default: DEFAULT_TASKS (quick: [pendulum, Hopper-v5])
    sizes: list[int] | None = None  # batch sizes N (default 1024 4096 16384 65536; quick: [4])
    modes: list[str] | None = None  # eager, compiled, cudagraphs (default: all three)
    kinds: list[str] | None = None  # rollout, bptt (default: both)
    steps: int = checked(16, checks.positive_int)  # env steps per timed rollout
    window: int = checked(16, checks.positive_int)  # env steps per timed BPTT window
    budget_s: float = checked(600.0, checks.positive)  # for the whole run: later cells are skipped
    device: str = "cuda"  # cuda | cuda:<k> | cpu (cpu: the smoke run; cudagraphs is CUDA only)
    # the raw results (out=) of earlier runs on one machine: write their data file again (tables, date,
    # machine, commands), the runs' cells in the order given
    from_results: list[str] | None = None
    # the library's source lines that take the most time in one env step (device time on a GPU, CPU time on
    # the CPU), with the ops they run: where fusing or batching pays; 0 leaves them out
    hotspots: int = checked(0, checks.nonnegative_int)


TASK_OPTIONS = {"mujoco": {"contact": "mujoco"}, "smooth": {"contact": "smooth"},
                "recompute": {"recompute_in_backward": True}}


def make_task_env(task: str, n: int, device: str):
    """The env of a task spec ``NAME[:OPTION...]`` (``HalfCheetah-v5:smooth:recompute``, see `TASK_OPTIONS`)."""
    from torchrl_diffenvs import make_env

    name, *options = task.split(":")
    kwargs = {}
    for option in options:
        if option not in TASK_OPTIONS:
            raise SystemExit(f"gpu_throughput: unknown task option {option!r} in {task!r}; valid: {list(TASK_OPTIONS)}")
        kwargs.update(TASK_OPTIONS[option])
    return make_env(name, num_envs=n, seed=0, device=device, **kwargs)


def workload(env, kind: str, args):
    """The timed call of one cell and its env steps per env."""
    import torch

    if kind == "rollout":
        def run():
            with torch.no_grad():
                return env.rollout(args.steps, break_when_any_done=False)
        return run, args.steps
    net, policy = C.tanh_mlp_policy(env, env.float_dtype)
    start = env.reset()

    def run():
        net.zero_grad(set_to_none=True)
        out = env.rollout(args.window, policy, auto_reset=False, tensordict=start.clone(), break_when_any_done=False)
        (-out["next", "reward"].mean()).backward()
        return out["next", "reward"].detach()
    return run, args.window


def step_diagnostics(task: str, n: int, device: str) -> dict:
    """CUDA kernels launched and host-device synchronisations in one env step without gradient (on
    the CPU: the aten ops of one env step, the profiler's count)."""
    import torch

    env = make_task_env(task, n, device)
    if not device.startswith("cuda"):  # the CPU proxy of the kernels: aten ops (the profiler's count)
        td = env.rand_action(env.reset())
        with torch.no_grad():
            return {"aten_ops_per_step": C.aten_ops(lambda: env.step(td))}
    td = env.rand_step(env.reset())  # warm-up
    with torch.no_grad():
        torch.cuda.synchronize()
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
            env.rand_step(env.reset())
            torch.cuda.synchronize()
        kernels = sum(e.count for e in prof.key_averages() if e.device_type == torch.autograd.DeviceType.CUDA)
        # the reset's own kernels are counted too: subtract those of a reset alone
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
            env.reset()
            torch.cuda.synchronize()
        kernels -= sum(e.count for e in prof.key_averages() if e.device_type == torch.autograd.DeviceType.CUDA)
        td = env.reset()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            torch.cuda.set_sync_debug_mode("warn")
            try:
                env.rand_step(td)
            finally:
                torch.cuda.set_sync_debug_mode("default")
    # not the mode's own notice that it is a prototype; a warning carries the Python line that synchronised
    syncs = [f"{'/'.join(Path(w.filename).parts[-2:])}:{w.lineno}" for w in caught
             if "synchronizing" in str(w.message) and "prototype" not in str(w.message)]
    return {"kernels_per_step": kernels, "syncs_per_step": len(syncs),
            "sync_sites": {site: syncs.count(site) for site in dict.fromkeys(syncs)}}


def step_hotspots(task: str, n: int, device: str, top: int) -> list[dict]:
    """The ``top`` source lines of the library that take the most time in one env step without
    gradient (after a warm-up step): the device time of the kernels their torch calls launch on a
    GPU, CPU time on the CPU; each with its share of the step's total and its calls' counts. Each
    torch call is wrapped in a profiler range named by the library line that made it, or for the
    algebra helpers of `HELPER_MODULES` the line that called them (a torch function mode: the
    profiler's own Python stacks are not recorded by default)."""
    import collections

    import torch
    from torch.overrides import TorchFunctionMode

    import torchrl_diffenvs

    PACKAGE = str(Path(torchrl_diffenvs.__file__).parent) + os.sep  # the library's own files, not torch's

    class NameCallSites(TorchFunctionMode):
        def __torch_function__(self, func, types, args=(), kwargs=None):
            frame = sys._getframe(1)
            while frame is not None and (not frame.f_code.co_filename.startswith(PACKAGE)
                                         or frame.f_code.co_filename.endswith(HELPER_MODULES)):
                frame = frame.f_back
            if frame is None:
                return func(*args, **(kwargs or {}))
            site = f"{frame.f_code.co_filename.removeprefix(PACKAGE)}:{frame.f_lineno}"
            with torch.profiler.record_function(f"site {site} {getattr(func, '__name__', func)}"):
                return func(*args, **(kwargs or {}))

    env = make_task_env(task, n, device)
    cuda = device.startswith("cuda")
    activities = [torch.profiler.ProfilerActivity.CPU] + ([torch.profiler.ProfilerActivity.CUDA] if cuda else [])
    with torch.no_grad():
        td = env.rand_action(env.reset())
        env.step(td)
        td = env.rand_action(env.reset())
        if cuda:
            torch.cuda.synchronize()
        with torch.profiler.profile(activities=activities) as prof, NameCallSites():
            env.step(td)
            if cuda:
                torch.cuda.synchronize()
    cost = (lambda e: e.device_time_total) if cuda else (lambda e: e.cpu_time_total)
    seconds, calls = collections.Counter(), collections.defaultdict(collections.Counter)
    for event in prof.events():
        # the CPU-side range only: on CUDA the profiler also records each range as a GPU annotation of the
        # same name, whose time the CPU range's device time already holds
        if event.name.startswith("site ") and event.device_type == torch.autograd.DeviceType.CPU:
            _, site, call = event.name.split(" ", 2)
            seconds[site] += cost(event) / 1e6
            calls[site][call] += 1
    total = sum(seconds.values()) or 1.0  # the share is of the time attributed to the library's lines
    return [{"site": site, "ms": 1e3 * s, "share": s / total, "calls": dict(calls[site].most_common(4))}
            for site, s in seconds.most_common(top)]


def measure(task: str, n: int, mode: str, kind: str, args) -> dict:
    """One cell: warm-up (compiling) call, then ``repeats`` timed calls."""
    import torch

    from torchrl_diffenvs import compile_physics
    from torchrl_diffenvs.envs.rollout import compile_report

    row = {"task": task, "N": n, "mode": mode, "kind": kind}
    if mode == "cudagraphs" and kind == "bptt":  # compile_physics compiles windows with gradient without them
        return {**row, "error": NOT_APPLICABLE}
    if mode == "cudagraphs" and not args.device.startswith("cuda"):
        return {**row, "error": "CUDA graphs need device=cuda"}
    env = make_task_env(task, n, args.device)
    if mode != "eager":
        compile_physics(env, steps_per_chunk=8, **({"mode": "reduce-overhead"} if mode == "cudagraphs" else {}))
    run, steps = workload(env, kind, args)
    if args.device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats(args.device)
    if kind == "bptt":  # the warm-up call counts the bytes its graph saves for the backward
        with C.saved_for_backward() as saved:
            first, _ = C.timed(run)
        row["saved_kib_per_env_step"] = sum(saved.values()) / (n * steps) / 1024
    else:
        first, _ = C.timed(run)
    walls = [C.timed(run)[0] for _ in range(args.repeats or (1 if args.quick else 2))]
    row.update(steps=steps, first_call_s=first, wall_s=walls,
               env_steps_per_s=n * steps / statistics.median(walls))
    if args.device.startswith("cuda"):
        row["peak_memory_gib"] = torch.cuda.max_memory_allocated(args.device) / 2**30
    report = compile_report(env)
    if report is not None:
        row["fallback_reason"] = report["fallback_reason"]
        row["first_calls"] = report["first_call_seconds"]
    return row


def docs_tables(results: list[dict], diagnostics: dict, device: str) -> dict:
    # a cell the budget skipped was not measured: no row of its own
    cells = {(r["task"], r["N"], r["kind"], r["mode"]): r for r in results if r.get("error") != "skipped (budget)"}
    where = f"on {device}"

    def rate(task, n, kind, mode):
        if kind == "bptt" and mode == "cudagraphs":
            return "n/a"
        r = cells.get((task, n, kind, mode))
        if r is None:
            return "-"
        if "error" in r:
            return r["error"].splitlines()[0][:80]
        return C.fmt_rate(r["env_steps_per_s"])

    def first_call(task, n, kind, mode):
        r = cells.get((task, n, kind, mode))
        return "-" if r is None or "first_call_s" not in r else f"{r['first_call_s']:.0f}"

    def memory(task, n):  # of the eager BPTT cell
        r = cells.get((task, n, "bptt", "eager"), {})
        peak = f"{r['peak_memory_gib']:.1f}" if "peak_memory_gib" in r else "-"
        saved = f"{r['saved_kib_per_env_step']:.1f}" if "saved_kib_per_env_step" in r else "-"
        return [r.get("steps", "-"), peak, saved]

    keys = list(dict.fromkeys((r["task"], r["N"]) for r in results))  # in the order measured
    tables = {}
    for kind, title in (("rollout", "Env-steps/s without gradient"), ("bptt", "Env-steps/s of BPTT windows "
                                                                            "(forward and backward)")):
        rows = [[task, n, *[rate(task, n, kind, m) for m in MODES],
                 *[first_call(task, n, kind, m) for m in MODES[1:]], *(memory(task, n) if kind == "bptt" else [])]
                for task, n in keys if any((task, n, kind, m) in cells for m in MODES)]
        if rows:
            extra = ["window (env steps)", "eager: peak GiB", "eager: saved KiB per env-step"] if kind == "bptt" else []
            tables[kind] = C.data_table(f"{title}, wall clock, {where}",
                                        ["task", "N", *MODES, "compiled: first call s", "cudagraphs: first call s",
                                         *extra], rows)
    if diagnostics:
        tables["diagnostics"] = C.data_table(
            f"One env step without gradient {where}: CUDA kernels launched and host-device synchronisations "
            "(on a GPU), aten ops (on the CPU)",
            ["task", "N", "kernels per env step", "syncs per env step", "where they synchronise",
             "aten ops per env step (CPU)"],
            [[d.get("task", task), d["N"], d.get("kernels_per_step", "-"), d.get("syncs_per_step", "-"),
              ", ".join(d.get("sync_sites", {})) or "-", d.get("aten_ops_per_step", "-")]
             for task, d in diagnostics.items()])
    hot = [(task, h) for task, d in diagnostics.items() for h in d.get("hotspots", [])[:HOTSPOT_ROWS]]
    if hot:
        tables["hotspots"] = C.data_table(
            f"Where one env step without gradient spends its time {where}: the library's source lines whose torch "
            f"calls take the most (device time on a GPU), the top {HOTSPOT_ROWS} per task",
            ["task", "N", "source line", "ms", "share of the time attributed", "calls (most frequent)"],
            [[task, diagnostics[task]["N"], f"`{h['site']}`", f"{h['ms']:.1f}", f"{100 * h['share']:.1f}%",
              ", ".join(f"{name} x{count}" for name, count in h["calls"].items())] for task, h in hot])
    return tables


def main(argv=None) -> dict:
    args = parse_cli(GPUThroughputSettings, argv, __doc__)
    C.setup_threads(args.threads)
    if args.from_results is not None:
        import json

        raws = [json.loads(Path(path).read_text()) for path in args.from_results]
        machines = {raw["info"]["machine"] for raw in raws}
        if len(machines) > 1:
            raise SystemExit(f"from_results: the runs were measured on different machines {sorted(machines)}; "
                             "a data file renders one machine's")
        merged = {"results": [r for raw in raws for r in raw["results"]],
                  "diagnostics": {k: v for raw in raws for k, v in raw["diagnostics"].items()}}
        C.write_data(args, "gpu_throughput", docs_tables(merged["results"], merged["diagnostics"], machines.pop()),
                     measured=C.measured_from_raw(raws, "gpu_throughput.py"))
        return merged
    device = C.setup_device(args.device)
    import torch

    tasks = args.tasks or (["pendulum", "Hopper-v5"] if args.quick else list(DEFAULT_TASKS))
    sizes = args.sizes or ([4] if args.quick else [1024, 4096, 16384, 65536])
    modes, kinds = args.modes or list(MODES), args.kinds or list(KINDS)
    for name, chosen, valid in (("modes", modes, MODES), ("kinds", kinds, KINDS)):
        if set(chosen) - set(valid):
            raise SystemExit(f"{name}={chosen}: valid values are {list(valid)}")
    info = C.versions()
    info["machine"] = C.machine_name(device)
    C.print_header(f"throughput on {device}, wall clock", info)
    started = time.perf_counter()
    results, diagnostics = [], {}

    def save():
        C.write_data(args, "gpu_throughput", docs_tables(results, diagnostics, C.machine_name(device)), device)
        C.write_json("gpu_throughput" + ("_quick" if args.quick else ""),
                     {"benchmark": "gpu_throughput", "date": time.strftime("%Y-%m-%d", time.gmtime()), "info": info,
                      "diagnostics": diagnostics, "results": results},
                     args.out)

    for mode in modes:  # eager first: every task and size, before any compiling
        for task in tasks:
            for n in sizes:
                for kind in kinds:
                    if time.perf_counter() - started > args.budget_s:
                        results.append({"task": task, "N": n, "mode": mode, "kind": kind,
                                        "error": "skipped (budget)"})
                        continue
                    if mode == "eager" and task not in diagnostics:
                        try:
                            diagnostics[task] = {"N": n, **step_diagnostics(task, n, device)}
                            if args.hotspots:
                                diagnostics[task]["hotspots"] = step_hotspots(task, n, device, args.hotspots)
                        except Exception as err:  # a diagnostic must not cost the measurements
                            diagnostics[task] = {"N": n, "error": f"{type(err).__name__}: {err}"[:200]}
                    try:
                        row = measure(task, n, mode, kind, args)
                    except torch.cuda.OutOfMemoryError:
                        row = {"task": task, "N": n, "mode": mode, "kind": kind, "error": "out of memory"}
                    except Exception as err:
                        row = {"task": task, "N": n, "mode": mode, "kind": kind,
                               "error": f"{type(err).__name__}: {err}"[:300]}
                    if device.startswith("cuda"):
                        torch.cuda.empty_cache()
                    results.append(row)
                    print({k: v for k, v in row.items() if k not in ("wall_s", "first_calls")}, flush=True)
                    save()
    save()
    return {"results": results, "diagnostics": diagnostics}


if __name__ == "__main__":
    main()
