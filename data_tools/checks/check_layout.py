"""The library's shape, checked: imports point down, no private name crosses a module, limits on files and signatures.

Run by ``.ci/run`` (``python -m data_tools.checks.check_layout``) from the repository root; prints one line per
finding and exits 1 if there is any. ``--root DIR`` checks another checkout.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
MAX_FILE_LINES = 600
MAX_PARAMETERS = 15
MAX_TOP_LEVEL_NAMES = 25
MAX_README_LINES = 150
# A score family's class is named (isinstance) only in its own file.
FAMILIES = {
    "ECR": "scores/ecr",
    "ENMI": "scores/enmi",
    "NMI": "scores/nmi",
    "NCC": "scores/ncc",
    "Mixture": "scores/mixture",
}


def module_name(path: Path, root: Path) -> str:
    """The dotted module a file of the package holds."""
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def resolve(module: str, path: Path, node: ast.ImportFrom) -> str:
    """The absolute module an ``ImportFrom`` names."""
    if not node.level:
        return node.module or ""
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    package = package[: len(package) - (node.level - 1)]
    return ".".join(package + ([node.module] if node.module else []))


def type_checking_lines(tree: ast.Module) -> set[int]:
    """Lines under ``if TYPE_CHECKING:`` (imports for annotations only, no runtime edge)."""
    lines = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.body:
                lines.update(range(child.lineno, (child.end_lineno or child.lineno) + 1))
    return lines


def room(module: str) -> str:
    """The unit of the import graph: a subpackage (``enmi_torch.scores``) or a top-level module."""
    parts = module.split(".")
    return ".".join(parts[:2])


def find_cycle(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected component with more than one node (Tarjan)."""
    index, low, stack, on_stack, components, counter = {}, {}, [], set(), [], [0]

    def visit(node: str) -> None:
        index[node] = low[node] = counter[0]
        counter[0] += 1
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph.get(node, ())):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return components


def count_parameters(function: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """A signature's parameters, ``self``/``cls`` not counted, ``*args`` and ``**kwargs`` one each."""
    arguments = function.args
    names = [*arguments.posonlyargs, *arguments.args, *arguments.kwonlyargs]
    names = [argument for argument in names if argument.arg not in ("self", "cls")]
    return len(names) + bool(arguments.vararg) + bool(arguments.kwarg)


def top_level_names(root: Path) -> tuple[list[str], list[str]]:
    """``enmi_torch.__all__`` of the checkout at ``root`` and its names that do not import, read in a fresh process."""
    code = (
        "import enmi_torch, json\n"
        "missing = [n for n in enmi_torch.__all__ if not hasattr(enmi_torch, n)]\n"
        "print(json.dumps([list(enmi_torch.__all__), missing]))"
    )
    environment = {**os.environ, "PYTHONPATH": str(root)}
    completed = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, env=environment)
    if completed.returncode:
        raise RuntimeError(f"import enmi_torch failed in {root}: {completed.stderr.strip().splitlines()[-1]}")
    names, missing = json.loads(completed.stdout)
    return names, missing


def findings_of(root: Path) -> list[str]:
    """Every finding of the checkout at ``root``, one line each."""
    findings = []
    graph: dict[str, set[str]] = {}
    package = root / "enmi_torch"
    for path in sorted(package.rglob("*.py")):
        relative = path.relative_to(package).with_suffix("").as_posix()
        module = module_name(path, root)
        shown = path.relative_to(root)
        text = path.read_text()
        lines = text.count("\n")
        if lines > MAX_FILE_LINES:
            findings.append(f"{shown}: {lines} lines (at most {MAX_FILE_LINES})")
        tree = ast.parse(text)
        annotation_only = type_checking_lines(tree)
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.lineno not in annotation_only:
                target = resolve(module, path, node)
                if target.startswith("enmi_torch"):
                    if room(target) != room(module):
                        graph.setdefault(room(module), set()).add(room(target))
                    for alias in node.names:
                        private = alias.name.startswith("_") and not alias.name.startswith("__")
                        if private and target != module:
                            findings.append(f"{shown}:{node.lineno}: private name {alias.name} imported from {target}")
            elif isinstance(node, ast.Import) and node.lineno not in annotation_only:
                for alias in node.names:
                    if alias.name.startswith("enmi_torch") and room(alias.name) != room(module):
                        graph.setdefault(room(module), set()).add(room(alias.name))
            elif isinstance(node, ast.Call) and getattr(node.func, "id", None) in ("isinstance", "issubclass"):
                named = {getattr(n, "id", getattr(n, "attr", None)) for n in ast.walk(node.args[1])}
                for family in sorted(named & set(FAMILIES)):
                    if relative != FAMILIES[family]:
                        findings.append(
                            f"{shown}:{node.lineno}: isinstance on the score family {family} outside "
                            f"enmi_torch/{FAMILIES[family]}.py (ask the score instead)"
                        )
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not node.name.startswith("_"):
                count = count_parameters(node)
                if count > MAX_PARAMETERS:
                    findings.append(
                        f"{shown}:{node.lineno}: {node.name} takes {count} parameters (at most {MAX_PARAMETERS})"
                    )
    for component in find_cycle(graph):
        findings.append(f"import cycle among {', '.join(component)}")
    names, missing = top_level_names(root)
    if len(names) > MAX_TOP_LEVEL_NAMES:
        findings.append(f"enmi_torch.__all__ holds {len(names)} names (at most {MAX_TOP_LEVEL_NAMES})")
    findings += [f"enmi_torch.__all__ names {name}, which does not import" for name in missing]
    readme_lines = (root / "README.md").read_text().count("\n")
    if readme_lines > MAX_README_LINES:
        findings.append(f"README.md: {readme_lines} lines (at most {MAX_README_LINES})")
    return findings


def main(argv: list[str] | None = None) -> int:
    """Print every finding; 1 if there is any."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=ROOT, help="the checkout to check (default: this one)")
    arguments = parser.parse_args(argv)
    findings = findings_of(arguments.root.resolve())
    for line in findings:
        print(line)
    print(f"check_layout: {len(findings)} finding(s)")
    return 1 if findings else 0


if __name__ == "__main__":
    sys.exit(main())
