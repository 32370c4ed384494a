"""The package's structure: no import cycles (module-level or inside functions), and TorchRL's /
tensordict's private names touched only in ``_compat.py``."""
import ast
import re
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[2] / "torchrl_diffenvs"


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(path: Path, modules) -> set[str]:
    """Package modules imported anywhere in ``path`` (relative imports resolved; ``from pkg
    import mod`` counts as importing ``pkg.mod``)."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            submodules = [f"{target}.{alias.name}" for alias in node.names if f"{target}.{alias.name}" in modules]
            candidates = submodules if len(submodules) == len(node.names) else [target, *submodules]
        elif isinstance(node, ast.Import):
            candidates = [alias.name for alias in node.names]
        else:
            continue
        found.update(c for c in candidates if c.startswith("torchrl_diffenvs"))
    return found


def test_no_import_cycles():
    modules = {module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph = {}
    for name, path in modules.items():
        targets = set()
        for target in imports_of(path, modules):
            while target and target not in modules:  # "pkg.mod.attr" -> "pkg.mod"
                target = target.rpartition(".")[0]
            # importing a submodule runs its packages' __init__ too, but they are not what imports it back
            if target and target != name:
                targets.add(target)
        graph[name] = targets

    cycles = []

    def visit(node, stack, on_stack, done):
        on_stack.add(node)
        stack.append(node)
        for nxt in graph[node]:
            if nxt in on_stack:
                cycles.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in done:
                visit(nxt, stack, on_stack, done)
        stack.pop()
        on_stack.discard(node)
        done.add(node)

    done: set[str] = set()
    for node in graph:
        if node not in done:
            visit(node, [], set(), done)
    assert not cycles, "import cycles:\n" + "\n".join(" -> ".join(c) for c in cycles)


def test_private_torchrl_and_tensordict_names_only_in_compat():
    pattern = re.compile(r"from (torchrl|tensordict)[\w.]* import _\w|(torchrl|tensordict)\.[\w.]*\._\w|\._carrier\b"
                         r"|_new_unsafe|_post_step_mdp_hooks|_has_dynamic_specs|_compiled_step_and_maybe_reset")
    offenders = []
    for path in PACKAGE.rglob("*.py"):
        if path.name == "_compat.py":
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if pattern.search(line) and not line.lstrip().startswith("#"):
                offenders.append(f"{path.relative_to(PACKAGE.parent)}:{number}: {line.strip()}")
    assert not offenders, "private names outside _compat.py:\n" + "\n".join(offenders)


def test_building_envs_and_training_configs_imports_no_rendering():
    """Rendering (and Pillow, an optional extra) is imported only when something is drawn."""
    import subprocess
    import sys

    code = ("import sys, torchrl_diffenvs; from torchrl_diffenvs.training import config; "
            "[torchrl_diffenvs.make_env(n) for n in torchrl_diffenvs.list_envs()]; "
            "print(sorted(m for m in ('PIL', 'torchrl_diffenvs.rendering') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
