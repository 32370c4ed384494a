"""What the contact tests share: one physics step of ours from each of MuJoCo's states along a
trajectory it steps, against ``mj_step``; MuJoCo's own verdict on its solver's convergence. Not a
test module."""
from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from torchrl_diffenvs.articulated import RigidBodyTree, default_params, step
from torchrl_diffenvs.articulated.pipeline import invweight0


def gaps_to_mj_step(tree: RigidBodyTree, mm, data, steps: int, each: Callable | None = None) -> np.ndarray:
    """``mj_step`` ``steps`` times from ``data`` (calling ``each(data)`` after every step), then our
    step from each state before, all in one batch (the steps are independent: each starts from
    MuJoCo's state): the worst ``|qpos|``/``|qvel|`` gap of each step, ``[steps]``."""
    import mujoco

    before, after = [], []
    for _ in range(steps):
        before.append(np.r_[data.qpos, data.qvel])
        mujoco.mj_step(mm, data)
        after.append(np.r_[data.qpos, data.qvel])
        if each is not None:
            each(data)
    before = torch.as_tensor(np.array(before))
    params = {k: v.expand(steps, *v.shape) for k, v in default_params(tree.model).items()}
    params["contact_friction"] = torch.as_tensor(tree.contact_pair_friction).expand(steps, -1)
    result = step(tree, before[:, :mm.nq], before[:, mm.nq:], torch.zeros(steps, mm.nu, dtype=torch.float64), params,
                  mm.opt.timestep, tree.model.integrator, invweight0(tree, params))
    ours = torch.cat([result.qpos, result.qvel], dim=1).numpy()
    return np.abs(ours - np.array(after)).max(1)


def mujoco_converged(mm, data) -> bool:
    """MuJoCo's own verdict after mj_forward: its solver stopped before ``opt.iterations``, or its
    last iteration met the tolerance (engine_solver.c: scaled improvement or gradient below it)."""
    used = int(data.solver_niter[0])
    last = data.solver[used - 1]
    return used < mm.opt.iterations or last.improvement < mm.opt.tolerance or last.gradient < mm.opt.tolerance
