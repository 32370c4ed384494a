"""The simulator's small batched products, two ways, on one device: ``@`` (a batched GEMM) and a
broadcast product summed over the shared axis (one elementwise kernel and one reduction).

An env step of a MuJoCo task is mostly products of 3x3 to 30x9 matrices, one per env and body
or row. Which form is faster depends on the device: on the CPU ``@`` is (a batched GEMM reads
each operand once; the broadcast form writes a larger intermediate), on a GPU a batched GEMM of
such small blocks can take longer than the elementwise kernels. The simulator picks the form per
device (`torchrl_diffenvs.articulated.spatial.small_matmul`, whose two forms this benchmark times;
a matrix-vector product is a product with a ``k x 1`` matrix), at the step's shapes, interleaved,
so that the choice rests on numbers: the median of ``repeats`` rounds, each call timed until the
device is done. Also the step's solves: ``linalg.solve_ex`` against a Cholesky factorisation and
solve at each task's ``nv`` (`torchrl_diffenvs.articulated.spatial.solve_spd` picks the faster per
device), and ``argsort`` of the line search's row breakpoints against ``sort``.

    python benchmarks/batched_products.py                       # device=cuda, N = 65536
    python benchmarks/batched_products.py device=cpu n=1024     # the CPU's side
"""
from __future__ import annotations

import statistics
import sys
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torchrl_diffenvs import checks  # noqa: E402
from torchrl_diffenvs.articulated.spatial import solve_spd, small_matmul  # noqa: E402
from torchrl_diffenvs.checks import checked, parse_cli  # noqa: E402


@dataclass(frozen=True)
class BatchedProductsSettings(C.BenchmarkSettings):
    device: str = "cuda"  # cuda | cuda:<k> | cpu
    n: int = checked(65536, checks.positive_int)  # envs in the batch
    dtype: str = checked("float32", checks.one_of(("float32", "float64")))


# (name, left shape, right shape) per env: HalfCheetah's 9 bodies and dofs, up to 30 constraint rows
SHAPES = (
    ("body rotations @ rotations", (9, 3, 3), (9, 3, 3)),
    ("body rotations @ model constants", (9, 3, 3), None),  # right: [9, 3, 3] shared by every env
    ("body rotations @ vectors", (9, 3, 3), (9, 3, 1)),
    ("6x6 inertias @ motion axes", (9, 6, 6), (9, 6, 1)),
    ("constraint Jacobian @ qacc", (30, 9), (9, 1)),
    ("mass matrix @ vector", (9, 9), (9, 1)),
    ("J' (W J)", (9, 30), (30, 9)),
)


def main(argv=None) -> dict:
    args = parse_cli(BatchedProductsSettings, argv, __doc__)
    C.setup_threads(args.threads)
    device = C.setup_device(args.device)
    import torch

    dtype = getattr(torch, args.dtype)
    n = 64 if args.quick else args.n
    rounds = args.repeats or (2 if args.quick else 20)
    gen = torch.Generator(device=device).manual_seed(0)

    def rand(*shape):
        return torch.randn(*shape, generator=gen, device=device, dtype=dtype)

    rows = []
    for name, left, right in SHAPES:
        a = rand(n, *left)
        b = rand(*left) if right is None else rand(n, *right)
        timings = C.interleaved({"matmul": lambda: a @ b, "broadcast": lambda: small_matmul(a, b, broadcast=True)},
                                rounds)
        assert torch.allclose(a @ b, small_matmul(a, b, broadcast=True), rtol=1e-4, atol=1e-4)
        us = {k: 1e6 * statistics.median(v["wall"]) for k, v in timings.items()}
        rows.append({"op": name, "matmul_us": us["matmul"], "broadcast_us": us["broadcast"]})
        print(rows[-1], flush=True)
    solves = []
    for size, task in ((9, "HalfCheetah"), (14, "the Ant"), (27, "the humanoids")):  # each task's nv
        spd = rand(n, size, size)
        spd = spd @ spd.transpose(-1, -2) + size * torch.eye(size, device=device, dtype=dtype)
        rhs = rand(n, size)
        timings = C.interleaved({"solve_ex": lambda: torch.linalg.solve_ex(spd, rhs)[0],
                                 "cholesky": lambda: solve_spd(spd, rhs, by_cholesky=True)}, rounds)
        assert torch.allclose(torch.linalg.solve_ex(spd, rhs)[0], solve_spd(spd, rhs, by_cholesky=True),
                              rtol=1e-3, atol=1e-4)
        us = {k: 1e6 * statistics.median(v["wall"]) for k, v in timings.items()}
        solves.append({"op": f"{size}x{size} solve ({task})", "solve_ex_us": us["solve_ex"], "cholesky_us": us["cholesky"]})
        print(solves[-1], flush=True)
    breakpoints = rand(n, 30)
    timings = C.interleaved({"argsort": lambda: breakpoints.argsort(-1), "sort": lambda: breakpoints.sort(-1)}, rounds)
    us = {k: 1e6 * statistics.median(v["wall"]) for k, v in timings.items()}
    rows += solves
    rows.append({"op": "argsort of 30 breakpoints", "argsort_us": us["argsort"], "sort_us": us["sort"]})
    print(rows[-1], flush=True)
    info = C.versions()
    info["machine"] = C.machine_name(device)
    C.write_json("batched_products", {"benchmark": "batched_products", "date": C.today(), "info": info, "n": n,
                                      "dtype": args.dtype, "rows": rows}, args.out)
    table = C.data_table(
        f"Microseconds per call at N = {n} ({args.dtype}) on {info['machine']}: the simulator's batched products "
        "as `@` and as a broadcast product summed",
        ["product (per env)", "@", "broadcast and sum", "broadcast / @"],
        [[r["op"], f"{r['matmul_us']:.0f}", f"{r['broadcast_us']:.0f}", C.fmt_ratio(r["broadcast_us"] / r["matmul_us"])]
         for r in rows if "matmul_us" in r])
    solve_table = C.data_table(
        f"Microseconds per call at N = {n} ({args.dtype}) on {info['machine']}: the solves of symmetric "
        "positive definite matrices (mass matrices, the constraint solver's Hessians) by the general solve "
        "and by a Cholesky factor",
        ["solve (per env)", "linalg.solve_ex", "cholesky_ex + cholesky_solve", "Cholesky / general"],
        [[r["op"], f"{r['solve_ex_us']:.0f}", f"{r['cholesky_us']:.0f}", C.fmt_ratio(r["cholesky_us"] / r["solve_ex_us"])]
         for r in solves])
    C.write_data(args, f"batched_products_{'cpu' if device == 'cpu' else 'gpu'}",
                 {"products": table, "solves": solve_table}, device)
    return {"rows": rows}


if __name__ == "__main__":
    main()
