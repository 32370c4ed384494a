"""Every ```python block of the documentation (``README.md`` and ``docs/**/*.md``) runs as written.

One case per page: the page's blocks run in order in one fresh namespace (a later block may use
the names an earlier block of the same page defined, as a reader running them would), in
pytest's ``tmp_path`` (files the snippets write land there), on one torch thread. A block that
truly cannot run here is marked on the line right before its fence with
``<!-- snippet: skip (reason) -->``: it is only compiled (a syntax check), not run, and the case
reports it with its reason (a warning; a page whose every block is marked is skipped). A failure
names the page, the block (its line in the page and its first line) and the exception;
tracebacks name the block as ``page:line``.

Registrations the snippets make (``register_env``, ``register_drawer``, ``register_learner`` and
the Hydra config it stores) are undone after each case, so two pages may register the same
example name and the other tests see the registries as they were.
"""
from __future__ import annotations

import linecache
import re
import textwrap
import traceback
import warnings
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[2]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]

FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>`{3,}|~{3,})[ \t]*(?P<info>[^`]*?)[ \t]*$")
MARKER = re.compile(r"^\s*<!--\s*snippet:")
SKIP = re.compile(r"^\s*<!--\s*snippet:\s*skip\s*\((?P<reason>[^()]*\S[^()]*)\)\s*-->\s*$")


@dataclass(frozen=True)
class Block:
    """One ```python block: the page line of its first code line, its code, why it is not run (or None)."""

    line: int
    source: str
    skip: str | None

    @property
    def first_line(self) -> str:
        return next((text.strip() for text in self.source.splitlines() if text.strip()), "")


def python_blocks(page: Path) -> list[Block]:
    """The page's ```python blocks in order; other fenced blocks (bash, yaml, ...) are passed over."""
    lines = page.read_text(encoding="utf-8").splitlines()
    blocks, i = [], 0
    while i < len(lines):
        opening = FENCE.match(lines[i])
        if not opening:
            i += 1
            continue
        fence, indent, info = opening["fence"], opening["indent"], opening["info"]
        end = i + 1
        while end < len(lines):  # the closing fence: the same character, at least as long, no info string
            closing = FENCE.match(lines[end])
            if closing and closing["fence"][0] == fence[0] and len(closing["fence"]) >= len(fence) \
                    and not closing["info"]:
                break
            end += 1
        if info.split()[:1] == ["python"]:
            previous = lines[i - 1] if i else ""
            skip = None
            if MARKER.match(previous):
                marked = SKIP.match(previous)
                if not marked:
                    raise ValueError(f"{page.relative_to(REPO)}:{i}: a snippet marker reads "
                                     f"'<!-- snippet: skip (reason) -->', got {previous.strip()!r}")
                skip = marked["reason"].strip()
            body = [text[len(indent):] if text.startswith(indent) else text.lstrip() for text in lines[i + 1:end]]
            blocks.append(Block(i + 2, textwrap.dedent("\n".join(body)) + "\n", skip))
        i = end + 1
    return blocks


CASES = [page for page in PAGES if python_blocks(page)]


def _snapshot(tree: dict) -> dict:
    return {key: _snapshot(value) if isinstance(value, dict) else value for key, value in tree.items()}


def _restore(tree: dict, saved: dict) -> None:
    """Puts a ``_snapshot`` back into ``tree`` in place (nested dicts too, keeping their identity)."""
    nested = {key: value for key, value in tree.items() if isinstance(value, dict)}
    tree.clear()
    for key, value in saved.items():
        if isinstance(value, dict):
            inner = nested.get(key, {})
            _restore(inner, value)
            value = inner
        tree[key] = value


@pytest.fixture
def registries():
    """Undoes what a page's snippets register: tasks, drawers, learners, Hydra's ``loss`` configs."""
    from hydra.core.config_store import ConfigStore

    import torchrl_diffenvs.envs.registry as env_registry
    import torchrl_diffenvs.rendering.core as drawings
    from torchrl_diffenvs.learners import LEARNERS

    tables = [env_registry._REGISTRY, env_registry._DRAWERS, drawings._DRAWERS, LEARNERS]
    saved = [dict(table) for table in tables]
    store = ConfigStore.instance().repo
    saved_store = _snapshot(store)
    yield
    for table, before in zip(tables, saved):
        table.clear()
        table.update(before)
    _restore(store, saved_store)


def run_blocks(name: str, blocks: list[Block]) -> list[str]:
    """Runs the blocks in order in one namespace; returns the blocks marked skip, with their reasons."""
    namespace = {"__name__": "__main__"}
    skipped = []
    for number, block in enumerate(blocks, 1):
        where = f"{name}: block {number} at line {block.line} ({block.first_line!r})"
        filename = f"{name}:{block.line}"
        linecache.cache[filename] = (len(block.source), None, block.source.splitlines(True), filename)
        failure = None
        try:
            code = compile(block.source, filename, "exec")
            if block.skip is not None:
                skipped.append(f"{where}: {block.skip}")
                continue
            exec(code, namespace)
        except Exception as error:  # any failure of a snippet is the case's failure
            failure = f"{where} failed: {type(error).__name__}: {error}\n\n{''.join(traceback.format_exception(error))}"
        if failure is not None:
            pytest.fail(failure, pytrace=False)
    return skipped


@pytest.mark.parametrize("page", CASES, ids=[page.relative_to(REPO).as_posix() for page in CASES])
def test_python_snippets_run(page: Path, tmp_path, monkeypatch, registries):
    monkeypatch.chdir(tmp_path)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    blocks = python_blocks(page)
    try:
        skipped = run_blocks(page.relative_to(REPO).as_posix(), blocks)
    finally:
        torch.set_num_threads(threads)
    if len(skipped) == len(blocks):
        pytest.skip("every block is marked skip: " + "; ".join(skipped))
    for reason in skipped:
        warnings.warn(f"not run (marked skip): {reason}", UserWarning, stacklevel=1)
