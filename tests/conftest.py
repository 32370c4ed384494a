"""What the test areas share.

Layout: one folder per area (``envs/``, ``simulator/``, ``rollout/``, ``learners/``,
``training/``, ``rendering/``, ``project/``). ``tests/`` itself is on ``sys.path``
(``pythonpath`` in pyproject.toml), so every test file imports the shared helpers as plain
modules: ``_env_helpers`` (env lists, builders, the script loader) and the workers that the
data-parallel tests start (``_distributed_workers``, ``_nonfinite_workers``).

Fixtures:

* ``train_script``: ``sota_scripts/train.py`` loaded as a module once per session (its
  ``run`` and ``validate_config`` are what the command line calls).
"""
from __future__ import annotations

import pytest

from _env_helpers import REPO, load_script


@pytest.fixture(scope="session")
def train_script():
    return load_script("train_script_fixture", REPO / "sota_scripts" / "train.py")
