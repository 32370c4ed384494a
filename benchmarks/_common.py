"""Shared harness of the benchmark scripts: arguments, timing, tables, JSON.

Measurement rules (the machine these run on is usually shared, 2 CPU cores):

* one torch intra-op thread by default (``threads=2`` for two); the count is recorded;
* candidates are timed *interleaved*: round ``r`` runs every candidate once, so a burst of load
  from another process hits all of them; ratios are taken within a round, then the median
  over rounds is reported;
* every timing records wall-clock time and the process's CPU time (user + system, which
  includes page faults). On a busy machine the wall clock also counts the time the process
  waited for a core; CPU time does not, so CPU-time rates and ratios are the steadier ones.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import platform
import resource
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from torchrl_diffenvs import checks
from torchrl_diffenvs.checks import Settings, checked

REPO_ROOT = Path(__file__).resolve().parent.parent
RESULTS_DIR = Path(__file__).resolve().parent / "results"
# The documentation renders its measured tables from these files (docs/hooks/generate.py)
DATA_DIR = Path(__file__).resolve().parent.parent / "docs" / "data"


@dataclass(frozen=True)
class BenchmarkSettings(Settings):
    """What every benchmark takes (``key=value`` arguments, as the training script and the demos)."""

    quick: bool = checked(False, checks.boolean)  # tiny sizes and 2 repeats: a smoke run in seconds
    threads: int = checked(1, checks.one_of((1, 2)))  # torch intra-op threads
    repeats: int | None = None  # timed rounds per configuration (default: the script's)
    out: str | None = None  # JSON output path (default benchmarks/results/<name>.json)
    # the documentation's data file to (re)write: docs/data/<data>.json (default: the script's
    # own name; quick=true writes none unless data= is given); none: write no data file
    data: str | None = None


_SYNCHRONIZE: list = []  # torch.cuda.synchronize when timing on a GPU


def setup_device(device: str) -> str:
    """Checks ``device=`` and makes :func:`timed` wait for the GPU; returns the device."""
    import torch

    try:
        resolved = torch.device(device)
    except (RuntimeError, TypeError):
        raise SystemExit(f"device={device!r}: expected cpu, cuda or cuda:<index>") from None
    if resolved.type == "cuda":
        if not torch.cuda.is_available():
            raise SystemExit(f"device={device!r}: torch.cuda.is_available() is False on this machine")
        _SYNCHRONIZE[:] = [torch.cuda.synchronize]
    elif resolved.type != "cpu":
        raise SystemExit(f"device={device!r}: expected cpu, cuda or cuda:<index>")
    return device


def setup_threads(threads: int) -> None:
    import torch

    torch.set_num_threads(threads)
    # gymnasium's numpy and any BLAS follow the same limit
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(var, str(threads))


def versions() -> dict:
    import gymnasium
    import numpy
    import tensordict
    import torch
    import torchrl

    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torchrl": torchrl.__version__,
        "tensordict": tensordict.__version__,
        "gymnasium": gymnasium.__version__,
        "numpy": numpy.__version__,
        "torch_threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "cpu_model": cpu_model(),
        "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "platform": platform.platform(),
        "command": " ".join([Path(sys.argv[0]).name, *portable_args(sys.argv[1:])]),
    }


def portable_args(args: Sequence[str]) -> list[str]:
    """The arguments of a command as anyone can rerun them from the repository root: paths inside
    the repository relative to it, ``data=`` the data file's name (``docs/data/<name>.json``),
    ``out=`` and ``resume=`` dropped when they name a scratch file outside the repository (the data
    file holds the tables the docs show), and ``keep_runs=`` with its ``resume=true`` dropped when it
    names a scratch directory there (a kept run continued across sittings reads as one run). In a
    list value (``summarise=[a.json,b.json]``) a scratch file is named by its file name alone; a
    word with a ``*`` pattern is quoted, as a shell needs it."""
    root = str(REPO_ROOT) + os.sep
    keeps_scratch = any(w.startswith("keep_runs=") and _scratch(w.partition("=")[2]) for w in args)
    words = []
    for word in args:
        key, eq, value = word.partition("=")
        if eq and key == "data" and (value.endswith(".json") or "/" in value):
            word = f"data={Path(value).stem}"
        elif eq and key in ("out", "resume", "keep_runs") and _scratch(value):
            continue
        elif eq and key == "resume" and keeps_scratch:
            continue
        elif eq and value.startswith("[") and value.endswith("]"):
            items = [portable_path(item) for item in value[1:-1].split(",")]
            word = f"{key}=[{','.join(items)}]"
        word = word.replace(root, "")
        words.append(f'"{word}"' if "*" in word else word)
    return words


def _scratch(value: str) -> bool:
    """Whether ``value`` names a path outside the repository (this machine's own)."""
    return os.path.isabs(value) and not value.startswith(str(REPO_ROOT) + os.sep)


def portable_path(value: str) -> str:
    """A path as a data file records it: inside the repository relative to its root, elsewhere
    (a scratch file of this machine) its file name alone; other values as they are."""
    if _scratch(value):
        return Path(value).name
    return value.replace(str(REPO_ROOT) + os.sep, "")


def portable_run(result: dict, runs_root: Path) -> dict:
    """A training run's record (``train.py``'s ``run``) with its run directory and checkpoint
    relative to the directory that holds the runs (a scratch directory of this machine), or to
    the run directory's parent where it lies elsewhere."""
    run_dir = Path(result["run_dir"]) if result.get("run_dir") else None
    root = runs_root if run_dir is None or run_dir.is_relative_to(runs_root) else run_dir.parent
    for key in ("run_dir", "checkpoint"):
        if result.get(key):
            path = Path(result[key])
            result[key] = str(path.relative_to(root)) if path.is_relative_to(root) else path.name
    return result


def print_header(title: str, info: dict) -> None:
    print(f"# {title}")
    for key, value in info.items():
        print(f"#   {key}: {value}")


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def timed(fn: Callable[[], object]) -> tuple[float, float]:
    """(wall seconds, CPU seconds) of one call; the result is dropped before returning."""
    wall, cpu = time.perf_counter(), cpu_seconds()
    result = fn()
    for synchronize in _SYNCHRONIZE:  # GPU work counts until it is done
        synchronize()
    wall, cpu = time.perf_counter() - wall, cpu_seconds() - cpu
    del result
    return wall, cpu


def aten_ops(fn: Callable[[], object]) -> int:
    """The aten ops one call of ``fn`` dispatches on the CPU (the profiler's count of ``aten::``
    events, nested ones included): the CPU proxy of the kernels it would launch on a GPU."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        fn()
    return sum(e.count for e in prof.key_averages() if e.key.startswith("aten::"))


def interleaved(candidates: dict[str, Callable[[], object]], rounds: int, warmup: int = 1) -> dict[str, dict]:
    """Times each candidate ``rounds`` times, round-robin; returns per-candidate lists."""
    for fn in candidates.values():
        for _ in range(warmup):
            fn()
    out = {name: {"wall": [], "cpu": []} for name in candidates}
    for _ in range(rounds):
        for name, fn in candidates.items():
            wall, cpu = timed(fn)
            out[name]["wall"].append(wall)
            out[name]["cpu"].append(cpu)
    return out


def spread(values: Sequence[float]) -> dict:
    return {"min": min(values), "median": statistics.median(values), "max": max(values)}


def median_ratio(numerator: Sequence[float], denominator: Sequence[float]) -> float:
    """Median over rounds of ``numerator[r] / denominator[r]``."""
    return statistics.median(a / b for a, b in zip(numerator, denominator))


def fmt_rate(x: float | None) -> str:
    if x is None:
        return "-"
    for unit, scale in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if x >= scale:
            return f"{x / scale:.3g}{unit}"
    return f"{x:.3g}"


def fmt_return(x: float | None) -> str:
    """A return as people read it: whole numbers from 100 up (``1450``, not ``1.45e+03``), three
    significant digits below."""
    if x is None:
        return "-"
    return f"{x:.0f}" if math.isfinite(x) and abs(x) >= 100 else f"{x:.3g}"


def fmt_error(x: float | None) -> str:
    """An error or distance as people read it: ``0``, two significant digits from 0.01 to 1000
    (``3.3``), a power of ten outside (``1.2e-07``)."""
    if x is None:
        return "-"
    if x == 0:
        return "0"
    # .2g would write 150 as 1.5e+02: round to two digits, then print without an exponent
    return f"{float(f'{x:.2g}'):g}" if 0.01 <= abs(x) < 1000 else f"{x:.1e}"


def fmt_ratio(x: float | None) -> str:
    return "-" if x is None else (f"{x:.3g}x" if x < 100 else f"{x:.0f}x")


def print_table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """Prints (and returns) a Markdown table."""
    cells = [[str(c) for c in headers]] + [[str(c) for c in row] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = ["| " + " | ".join(c.ljust(w) for c, w in zip(r, widths)) + " |" for r in cells]
    lines.insert(1, "|" + "|".join("-" * (w + 2) for w in widths) + "|")
    text = "\n".join(lines)
    print(text)
    return text


def cpu_model() -> str:
    """This machine's CPU model (``/proc/cpuinfo``'s model name; elsewhere ``platform.processor()``)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:  # not Linux: platform.processor() it is
        pass
    return platform.processor() or platform.machine()


def machine_name(device: str = "cpu", threads: int | None = None, models: Sequence[str] = ()) -> str:
    """The machine in words, for the data files: CPU model and count, architecture, torch threads
    (this process's, or ``threads``: those of the runs a summary reads) and, on CUDA, the GPU.
    ``models``: the CPU models the summarised runs recorded, named instead of this machine's."""
    import torch

    model = " / ".join(dict.fromkeys(models)) or cpu_model()
    threads = torch.get_num_threads() if threads is None else threads
    text = f"{os.cpu_count()}-vCPU {model} ({platform.machine()}), {threads} torch thread{'s' if threads > 1 else ''}"
    if str(device).startswith("cuda") and torch.cuda.is_available():
        text += f", {torch.cuda.get_device_name(torch.device(device))}"
    return text


def data_table(title: str, headers: Sequence[str], rows: Sequence[Sequence[object]]) -> dict:
    """One table of a data file: cells as the benchmark prints them."""
    return {"title": title, "columns": [str(c) for c in headers], "rows": [[str(c) for c in row] for row in rows]}


def today() -> str:
    """Today's date (UTC), as the data files give it."""
    return datetime.now(timezone.utc).date().isoformat()


def measured_from_raw(raws: Sequence[dict], script: str) -> dict:
    """``measured=`` for :func:`write_data` from earlier runs' raw results (their ``out=`` files):
    the newest date, their machines and their commands without ``out=``/``data=`` (local files)."""
    commands = []
    for raw in raws:
        words = [w for w in raw["info"]["command"].split()[1:] if not w.startswith(("out=", "data="))]
        commands.append(" ".join([f"python benchmarks/{script}", *words]))
    dates = [raw["date"] for raw in raws if raw.get("date")]
    return {"date": max(dates) if dates else None, "machine": "; ".join(sorted({raw["info"]["machine"] for raw in raws})),
            "command": "; ".join(commands)}


def _script(name: str, source: str | None = None) -> str:
    """The benchmark script this process runs (its own file, or ``<source or name>.py`` when called
    from elsewhere, e.g. a test)."""
    return Path(sys.argv[0]).name if Path(sys.argv[0]).suffix == ".py" else f"{source or name}.py"


def command_line(name: str, source: str | None = None) -> str:
    """This process's command as :func:`write_data` records it (:func:`portable_args`)."""
    return " ".join(["python", f"benchmarks/{_script(name, source)}", *portable_args(sys.argv[1:])])


def data_path(settings: BenchmarkSettings, name: str) -> Path | None:
    """The data file :func:`write_data` writes for these settings (``None``: it writes none)."""
    target = getattr(settings, "data", None)
    if target == "none" or (target is None and getattr(settings, "quick", False)):
        return None
    return Path(target) if target and (target.endswith(".json") or "/" in target) else DATA_DIR / f"{target or name}.json"


def write_data(settings: BenchmarkSettings, name: str, tables: dict[str, dict], device: str = "cpu",
               source: str | None = None, measured: dict | None = None) -> Path | None:
    """Writes the tables the documentation shows (:func:`data_table` each, by key) to
    ``docs/data/<settings.data or name>.json`` with today's date (UTC), the machine and the command,
    so the next measurement replaces the one the docs show. Quick runs write nothing unless
    ``data=`` names a file; ``data=none`` writes nothing. ``measured``: ``{"date", "machine",
    "command"}`` of a measurement made earlier or elsewhere whose results these tables render."""
    path = data_path(settings, name)
    if path is None:
        return None
    measured = measured or {}
    payload = {
        "measured": measured.get("date") or today(),
        "machine": measured.get("machine") or machine_name(device),
        "command": measured.get("command") or command_line(name, source),
        "source": f"benchmarks/{source}.py" if source else f"benchmarks/{_script(name)}",
        "tables": tables,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=1, ensure_ascii=False) + "\n")
    print(f"# wrote {path}")
    return path


def table_cells(text: str) -> tuple[list[str], list[list[str]]]:
    """Headers and rows of a table printed by :func:`print_table` (cells without ``|``)."""
    lines = [line for line in text.splitlines() if line.strip() and set(line) - set("|- ")]
    cells = [[c.strip() for c in line.strip()[1:-1].split("|")] for line in lines]
    return cells[0], cells[1:]


def write_json(name: str, payload: dict, out: str | Path | None) -> Path:
    path = Path(out) if out is not None else RESULTS_DIR / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=1, default=str) + "\n")
    print(f"# wrote {path}")
    return path


def tanh_mlp_policy(env, dtype, seed: int = 0):
    """A deterministic 64-64 tanh MLP policy scaled into the action bounds (the BPTT windows the
    compile and GPU benchmarks time), as a plain module and a TensorDictModule writing ``"action"``."""
    import torch
    from tensordict.nn import TensorDictModule

    torch.manual_seed(seed)
    net = torch.nn.Sequential(torch.nn.Linear(env.observation_dim, 64), torch.nn.Tanh(), torch.nn.Linear(64, 64),
                              torch.nn.Tanh(), torch.nn.Linear(64, env.action_dim), torch.nn.Tanh())
    net = net.to(device=env.device, dtype=dtype)
    scale = float(env.action_spec.space.high.flatten()[0])
    return net, TensorDictModule(lambda obs: net(obs) * scale, in_keys=["observation"], out_keys=["action"])


TRAIN_SCRIPT = Path(__file__).resolve().parent.parent / "sota_scripts" / "train.py"
CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def load_train_script():
    """``sota_scripts/train.py`` as a module: its ``run(cfg, run_dir, overrides)`` trains one configuration."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("train_script", TRAIN_SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def compose(overrides: list[str]):
    """The training script's configuration for these command-line overrides, composed by Hydra as the
    command line composes it (after :func:`load_train_script` has registered the generated sections)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return hydra_compose(config_name="config", overrides=overrides)


def storage_bytes(tensors, seen: dict) -> None:
    """Adds the storages of ``tensors`` to ``seen`` ({data pointer: bytes}: a storage counts once)."""
    for t in tensors:
        storage = t.untyped_storage()
        seen.setdefault(storage.data_ptr(), storage.nbytes())


@contextlib.contextmanager
def saved_for_backward():
    """``with saved_for_backward() as saved:`` the distinct storages autograd saves for the backward
    inside the block, ``{data pointer: bytes}`` (``torch.autograd.graph.saved_tensors_hooks``)."""
    import torch

    saved: dict = {}

    def pack(tensor):
        storage_bytes([tensor], saved)
        return tensor

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda tensor: tensor):
        yield saved
