"""The package's layout, read from the source: no import cycles, imports only down the floors that
README.md states, no hidden function-local imports of the package's own modules, and a README folder
map that names every module there is (and none that is not)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "src" / "instagram_hdmap"
README = ROOT / "README.md"
NAME = "instagram_hdmap"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def imports_of(module: str) -> list[tuple[str, int, bool]]:
    """``(imported module, line, inside a function)`` for every import of a package module in ``module``.
    ``from . import x`` and ``from .pkg import x`` count as imports of the submodule ``x`` where one exists."""
    path = MODULES[module]
    tree = ast.parse(path.read_text(), str(path))
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    local_lines = {n.lineno for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                   for n in ast.walk(f) if isinstance(n, (ast.Import, ast.ImportFrom))}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != NAME:
                continue
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                out.append((sub if sub in MODULES else target, node.lineno, node.lineno in local_lines))
        elif isinstance(node, ast.Import):
            out += [(a.name, node.lineno, node.lineno in local_lines) for a in node.names
                    if a.name.split(".")[0] == NAME]
    return out


GRAPH = {m: sorted({t for t, _, _ in imports_of(m) if t != m}) for m in MODULES}


def floors_from_readme() -> list[list[str]]:
    """The floors of README's "Imports run one way" paragraph, lowest first."""
    lines = README.read_text()[README.read_text().index("Imports run one way"):].splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("    "))
    block = []
    for line in lines[start:]:
        if not line.startswith("    "):
            break
        block.append(line.strip())
    return [[name.strip() for name in floor.split(",")] for floor in " ".join(block).split("->")]


def floor_of(module: str, floors: list[list[str]]) -> int:
    rel = module[len(NAME) + 1:] if module != NAME else "__init__"
    for i, floor in enumerate(floors):
        for name in floor:
            if rel == name or rel.startswith(name + "."):
                return i
    raise AssertionError(f"module {module} is on no floor of README's import floors; add it there")


def test_every_module_is_parsed_and_the_graph_is_not_empty():
    assert f"{NAME}.inference" in MODULES and f"{NAME}.data.synthetic.jobs" in MODULES
    assert f"{NAME}.inference" in GRAPH[f"{NAME}.predict"]
    assert f"{NAME}.distributed" in GRAPH[f"{NAME}.engine"]  # ``from . import distributed as du``


def find_cycle(graph: dict[str, list[str]]) -> list[str] | None:
    """One import cycle ``[a, b, ..., a]`` of ``graph``, or None (depth-first search, three colours)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in graph.get(node, []):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def test_find_cycle_finds_a_cycle_behind_two_steps():
    assert find_cycle({"a": ["b"], "b": ["c"], "c": ["a"], "d": ["a"]}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": ["b", "c"], "b": ["c"], "c": []}) is None


def test_no_import_cycles():
    cycle = find_cycle(GRAPH)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_imports_run_down_the_floors():
    floors = floors_from_readme()
    assert {"config", "geometry"} <= set(floors[0]) and "cli" in floors[-1]
    upward = [f"{m} (floor {floor_of(m, floors)}) imports {t} (floor {floor_of(t, floors)})"
              for m, targets in GRAPH.items() for t in targets if floor_of(t, floors) > floor_of(m, floors)]
    assert upward == []


def test_no_function_local_imports_of_the_package():
    """A function-local import hides an edge of the graph; the package's own modules are imported at
    the top (the optional extras [av2] and [deploy] are third-party packages, imported where used)."""
    local = [f"{MODULES[m].relative_to(ROOT)}:{line} imports {t}"
             for m in MODULES for t, line, inside in imports_of(m) if inside]
    assert local == []


# --- the README's folder map ---------------------------------------------------------------------------


def readme_map() -> dict[str, str]:
    """``{path relative to the package: description}`` of the Layout block's src/instagram_hdmap/ tree."""
    text = README.read_text()
    block = text[text.index("## Layout"):]
    block = block[block.index("```") + 3:]
    block = block[: block.index("```")]
    lines = block.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("src/instagram_hdmap/"))
    out, stack = {}, []
    for line in lines[start + 1:]:
        if not line.startswith("  "):
            break
        indent = (len(line) - len(line.lstrip())) // 2
        m = re.match(r"(\S+)\s*(.*)", line.strip())
        name, description = m.group(1), m.group(2)
        if not name.endswith((".py", "/")):  # a description continued on the next line
            continue
        stack = stack[: indent - 1]
        if name.endswith("/"):
            stack.append(name.rstrip("/"))
            out["/".join(stack) + "/"] = description
        else:
            out["/".join([*stack, name])] = description
    return out


def test_readme_map_names_every_module_and_only_those():
    named = readme_map()
    files = {str(p.relative_to(PACKAGE)) for p in PACKAGE.rglob("*.py")}
    folders = {str(p.relative_to(PACKAGE)) + "/" for p in PACKAGE.rglob("*") if p.is_dir() and
               (p / "__init__.py").is_file()} - {"./"}
    assert sorted(files - set(named)) == [], "modules missing from README's Layout"
    assert sorted(set(named) - files - folders) == [], "README's Layout names modules that do not exist"
    assert all(named[f] for f in files), "each module in README's Layout says what it holds"


@pytest.mark.parametrize("module", ["config", "files", "geometry", "errors"])
def test_the_lowest_floor_imports_nothing_above_itself(module):
    floors = floors_from_readme()
    assert all(floor_of(t, floors) == 0 for t in GRAPH[f"{NAME}.{module}"])


# --- the paper's equation numbers ------------------------------------------------------------------------


def test_equation_numbers_follow_the_paper():
    """The equation numbers quoted in the code are the paper's: equations are numbered in the order of
    their ``\\label{eq:...}`` in the .tex (every equation of the paper has one)."""
    tex = ROOT.parent / "shared" / "paper" / "instagram_paper.tex"
    if not tex.is_file():
        pytest.skip(f"the paper is not at {tex}")
    labels = re.findall(r"\\begin\{equation\}\s*\\label\{eq:([\w]+)\}", tex.read_text())
    number = {name: i + 1 for i, name in enumerate(labels)}
    assert number["embedding"] == 1 and len(number) == len(labels)
    expected = {
        "losses.py": [("loss_vertex", "cnn_loss"), ("loss_distance", "cnn_loss"), ("loss_adjacency", "adj_loss"),
                      ("loss_class", "gnn_loss"), ("sum of the weighted terms", "loss")],
        "assignment.py": [("Matching", "gt_pair")],
        "models/gnn.py": [("vertex embeddings", "embedding"), ("attentional GNN", "gnn"),
                          ("class and matching heads", "MLP"), ("scores", "score")],
    }
    wrong = []
    for file, pairs in expected.items():
        text = (PACKAGE / file).read_text()
        for phrase, label in pairs:
            m = re.search(re.escape(phrase) + r"[^\n]*?Eq\. (\d+)", text)
            assert m, f"{file}: no equation number after '{phrase}'"
            if int(m.group(1)) != number[label]:
                wrong.append(f"{file}: '{phrase}' quotes Eq. {m.group(1)}, the paper's is Eq. {number[label]}")
    assert wrong == []


# Rooms of one idea each: a reader holds a function, a class or a module in view at once.
MAX_LINES = {"function": 80, "class": 300, "module": 700}


def oversized(path: Path, root: Path = ROOT) -> list[str]:
    """The functions, methods and classes of ``path`` longer than ``MAX_LINES`` (from ``def`` / ``class`` to
    their last line, docstrings included), and the module itself if it is."""
    text = path.read_text()
    found = []
    if len(text.splitlines()) > MAX_LINES["module"]:
        found.append(f"{path.relative_to(root)}: module of {len(text.splitlines())} lines")
    for node in ast.walk(ast.parse(text, str(path))):
        kind = ("function" if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
                else "class" if isinstance(node, ast.ClassDef) else None)
        if kind is None:
            continue
        length = node.end_lineno - node.lineno + 1
        if length > MAX_LINES[kind]:
            found.append(f"{path.relative_to(root)}:{node.lineno}: {kind} {node.name} of {length} lines")
    return found


def test_no_room_is_too_long():
    found = [line for path in MODULES.values() for line in oversized(path)]
    assert not found, f"over {MAX_LINES}: split by idea:\n" + "\n".join(found)


def test_oversized_finds_a_long_function_a_long_class_and_a_long_module(tmp_path):
    body = "\n".join(f"    x{i} = {i}" for i in range(81))
    methods = "\n".join(f"    def m{i}(self):\n        return {i}\n" for i in range(101))
    path = tmp_path / "big.py"
    path.write_text(f"def long():\n{body}\n\n\ndef short():\n    return 1\n\n\nclass Big:\n{methods}\n"
                    + "x = 1\n" * 500)
    found = oversized(path, tmp_path)
    assert [line.split(": ", 1)[1].split(" of ")[0] for line in found] == ["module", "function long", "class Big"]
