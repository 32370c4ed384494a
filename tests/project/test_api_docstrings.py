"""Every object the API reference renders has a docstring: mkdocstrings leaves out a member without
one, so a public class, function, method or property without a docstring is missing from the site."""
from __future__ import annotations

import importlib
import inspect
import re
from pathlib import Path

DOCS = Path(__file__).resolve().parents[2] / "docs" / "api"


def rendered_modules() -> list[str]:
    return sorted({name for page in DOCS.glob("*.md")
                   for name in re.findall(r"^::: ([\w.]+)", page.read_text(), re.MULTILINE)})


def public_objects(path: str):
    try:
        module = importlib.import_module(path)
    except ModuleNotFoundError:  # ::: names an object, not a module
        parent, _, attr = path.rpartition(".")
        yield path, getattr(importlib.import_module(parent), attr)
        return
    names = getattr(module, "__all__", None) or [n for n in vars(module) if not n.startswith("_")]
    for name in names:
        obj = getattr(module, name)
        if (inspect.isclass(obj) or inspect.isfunction(obj)) and obj.__module__.startswith("torchrl_diffenvs"):
            yield f"{path}.{name}", obj


def own_members(cls):
    for name, member in vars(cls).items():
        if name.startswith("_"):
            continue
        function = member.fget if isinstance(member, property) else getattr(member, "__func__", member)
        if not callable(function):
            continue
        inherited = any((getattr(getattr(base, name, None), "__doc__", None) or "").strip() for base in cls.__mro__[1:])
        yield name, (function.__doc__ or "").strip() or inherited


def test_every_public_object_of_the_api_pages_has_a_docstring():
    modules = rendered_modules()
    assert "torchrl_diffenvs.envs" in modules and len(modules) > 20  # the pages were read
    missing = []
    for path in modules:
        for name, obj in public_objects(path):
            if not (obj.__doc__ or "").strip():
                missing.append(name)
            if inspect.isclass(obj):
                missing += [f"{name}.{member}" for member, documented in own_members(obj) if not documented]
    assert not missing, f"no docstring (so not on the API pages): {sorted(set(missing))}"
