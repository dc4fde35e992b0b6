"""Imports run one way, down the layers (docs/architecture.md): a module imports only from its
own layer or the layers before it. Read from the source with ``ast``, every import counted,
those inside functions too."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# the layers, lowest first; a module belongs to the longest prefix that names it
LAYERS = (
    "drivers",
    "uwbd.codec",
    "uwbd.journal",
    "uwbd.fusion.core",
    "uwbd.fusion.checks",
    "uwbd.fusion.models",
    "uwbd.fusion.settings",
    "uwbd.fusion.types",
    "uwbd.fusion.policy",
    "uwbd.fusion.filter",
    "uwbd.fusion",
    "uwbd.config",
    "uwbd.logs",
    "uwbd.ros2",
    "uwbd.service",
    "uwbd.tools",
    "uwbd.commands",
    "uwbd.cli",
    "uwbd.__main__",
)


def _module_of(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    files = [*ROOT.glob("uwbd/**/*.py"), *ROOT.glob("drivers/**/*.py")]
    return {_module_of(p): p for p in files}


def _layer(module: str) -> int | None:
    """The index of a module's layer; ``None`` for the package ``uwbd`` itself (its version)."""
    best = None
    for i, name in enumerate(LAYERS):
        if (module == name or module.startswith(name + ".")) and (
                best is None or len(name) > len(LAYERS[best])):
            best = i
    return best


def _imports(module: str, path: Path, known: set[str]) -> list[tuple[str, int]]:
    """The project modules a module imports, with the line of each import."""
    found = []
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*up, base] if base else up)
            # "from uwbd import journal" imports the module uwbd.journal
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                found.append((sub if sub in known else base, node.lineno))
    return [(name, line) for name, line in found
            if name.split(".")[0] in ("uwbd", "drivers")]


def test_every_module_has_a_layer() -> None:
    modules = _modules()
    lost = [m for m in modules if m != "uwbd" and _layer(m) is None]
    assert not lost, f"modules in no layer (add them to LAYERS): {lost}"


def test_imports_run_down_the_layers() -> None:
    modules = _modules()
    known = set(modules)
    upward = []
    for module, path in sorted(modules.items()):
        here = _layer(module)
        for name, line in _imports(module, path, known):
            there = _layer(name)
            if here is not None and there is not None and there > here:
                upward.append(f"{path.relative_to(ROOT)}:{line} {module} -> {name}")
    assert not upward, "imports running back up a layer:\n" + "\n".join(upward)


def test_the_check_sees_an_upward_import(tmp_path: Path) -> None:
    """The check itself: an import from a higher layer is found."""
    fake = tmp_path / "m.py"
    fake.write_text("from uwbd.service.pipeline import Pipeline\n", encoding="utf-8")
    found = _imports("uwbd.fusion.core.m", fake, {"uwbd.service.pipeline"})
    assert found == [("uwbd.service.pipeline", 1)]
    assert _layer("uwbd.service.pipeline") > _layer("uwbd.fusion.core.m")  # type: ignore[operator]
