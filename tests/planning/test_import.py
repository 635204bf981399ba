import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_planning_import_is_light():
    code = (
        "import sys, renderworld.planning, renderworld.world, renderworld.metrics\n"
        "heavy = [m for m in ('hydra', 'omegaconf', 'open3d') if m in sys.modules]\n"
        "assert not heavy, heavy\n"
        "print('ok')\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_public_names_are_exported():
    import renderworld.metrics as metrics
    import renderworld.planning as planning
    import renderworld.world as world

    for mod in (planning, world, metrics):
        assert mod.__all__ and all(hasattr(mod, n) for n in mod.__all__)


def _module_imports(package: str) -> tuple[dict[str, set[str]], list[tuple[str, str]]]:
    """Module-level imports between ``package``'s modules, and function-level ones."""
    import ast

    root = ROOT / package.replace(".", "/")
    mods = {}
    for path in root.rglob("*.py"):
        name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        mods[name.removesuffix(".__init__")] = path
    graph, nested = {m: set() for m in mods}, []
    for mod, path in mods.items():
        tree = ast.parse(path.read_text())
        top = {id(n) for n in tree.body}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            else:
                continue
            for target in (t for t in targets if t in mods and t != mod):
                (graph[mod].add(target) if id(node) in top else nested.append((mod, target)))
    return graph, nested


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph`` as a path, or None."""
    state: dict[str, int] = {}

    def visit(mod, path):
        state[mod] = 1
        for dep in sorted(graph[mod]):
            if state.get(dep) == 1:
                return path + [dep]
            if dep not in state and (found := visit(dep, path + [dep])):
                return found
        state[mod] = 2
        return None

    for mod in sorted(graph):
        if mod not in state and (found := visit(mod, [mod])):
            return found
    return None


def test_cycle_finder_finds_cycles():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None


def test_world_and_planning_have_no_import_cycles():
    for package in ("renderworld.world", "renderworld.planning"):
        graph, nested = _module_imports(package)
        assert not nested, f"function-level imports inside {package}: {nested}"
        assert _cycle(graph) is None, f"import cycle: {' -> '.join(_cycle(graph))}"
    graph, _ = _module_imports("renderworld.world")
    assert "renderworld.world.model" not in graph["renderworld.world.rollout"]
