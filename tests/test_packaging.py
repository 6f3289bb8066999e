"""The package's shape, read from the source: what the wheel ships, and who imports whom.

The repository keeps the app side in ``agents/`` and the configs in ``configs/``; both install
inside the package (``mpa_gym.agents``, ``mpa_gym.configs``, mapped in pyproject.toml). That a
built wheel, installed outside the repository, does what the README shows is checked by
``.ci/wheel-check`` (run by ``.ci/run``), not here: it builds and installs into fresh
environments, which takes minutes.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import tomllib
import yaml

import mpa_gym
from mpa_gym.analysis.scenario import load_scenario, scenario_names
from mpa_gym.configs import CONFIG_DIR, DEFAULT_TRAIN_CONFIG

ROOT = Path(__file__).resolve().parents[1]
# installed package -> the repository folder it is built from (pyproject's package-dir)
TREES = {"mpa_gym": ROOT / "mpa_gym", "mpa_gym.agents": ROOT / "agents",
         "mpa_gym.configs": ROOT / "configs"}
APP = "mpa_gym.agents"
CLI = "mpa_gym.agents.cli"  # loads each subcommand's modules on use (the train extra's among them)
# the app package exports the loader lazily (PEP 562 __getattr__): importing it for the command
# line must not pay ~0.7 s for the loader's imports
LAZY_EXPORTS = "mpa_gym.agents"


def _modules() -> Iterator[tuple[str, Path]]:
    for pkg, folder in TREES.items():
        for path in sorted(folder.rglob("*.py")):
            parts = path.relative_to(folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            yield ".".join((pkg, *parts)), path


MODULES = dict(_modules())


def _imports(path: Path) -> Iterator[tuple[str, int, bool]]:
    """(imported module, line, inside a function) for every import of ``path``; ``from P import
    N`` counts as importing P.N where that is a module, else P."""
    tree = ast.parse(path.read_text())
    local: set[int] = set()
    typing_only: set[int] = set()  # under ``if TYPE_CHECKING:``: never imported at run time
    for fn in ast.walk(tree):
        if isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
            local |= {id(n) for n in ast.walk(fn) if isinstance(n, ast.Import | ast.ImportFrom)}
        elif isinstance(fn, ast.If) and ast.unparse(fn.test) == "TYPE_CHECKING":
            typing_only |= {id(n) for n in ast.walk(fn)}
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno, id(node) in local
        elif isinstance(node, ast.ImportFrom) and node.module:
            for alias in node.names:
                sub = f"{node.module}.{alias.name}"
                yield (sub if sub in MODULES else node.module), node.lineno, id(node) in local


def test_every_package_folder_is_listed_for_the_wheel():
    on_disk = {name for name, path in MODULES.items() if path.name == "__init__.py"}
    # the configs' data-only folders, listed so that setuptools ships their files
    on_disk |= {f"mpa_gym.configs.{d.name}" for d in (ROOT / "configs").iterdir()
                if d.is_dir() and not d.name.startswith("__")}
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())
                 ["tool"]["setuptools"]["packages"])
    assert listed == on_disk


def test_the_shipped_configs_are_found_through_the_package():
    assert DEFAULT_TRAIN_CONFIG.is_file() and CONFIG_DIR == ROOT / "configs"
    names = scenario_names()
    for path in [*CONFIG_DIR.glob("scenarios/*.yaml"), *CONFIG_DIR.glob("rigs/*.yaml")]:
        assert path.stem in names
        assert load_scenario(path.stem).name  # every named scenario and rig loads by name


def test_the_version_is_defined_once():
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "version" in pyproject["project"]["dynamic"]
    assert pyproject["tool"]["setuptools"]["dynamic"]["version"] == {
        "attr": "mpa_gym.__version__"}
    assert mpa_gym.__version__.count(".") == 2
    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert str(citation["version"]) == mpa_gym.__version__  # the one place it is repeated


def test_sub_packages_are_attributes_of_the_package():
    assert mpa_gym.envs.MPALegEnv.__name__ == "MPALegEnv"  # help(mpa_gym.envs.MPALegEnv)
    with pytest.raises(AttributeError, match="nosuch"):
        mpa_gym.nosuch  # noqa: B018


def test_the_library_never_imports_the_app():
    bad = [f"{name}:{line} imports {imp}" for name, path in MODULES.items()
           if not name.startswith(APP) for imp, line, _ in _imports(path)
           if imp == APP or imp.startswith(f"{APP}.")]
    assert not bad


def test_nothing_imports_a_top_level_agents_module():
    # the name belongs to other distributions (the OpenAI Agents SDK installs one)
    paths = [*MODULES.values(), *sorted((ROOT / "tests").glob("*.py"))]
    bad = [f"{p.relative_to(ROOT)}:{line} imports {imp}" for p in paths
           for imp, line, _ in _imports(p) if imp == "agents" or imp.startswith("agents.")]
    assert not bad


def test_no_function_local_import_of_the_project_but_the_commands():
    # a function-local import of the project's own modules hides an import cycle; only the
    # command line defers its subcommands' modules (they need the train extra), and the app
    # package its lazy export (the cycle test below counts both)
    bad = [f"{name}:{line} imports {imp}" for name, path in MODULES.items()
           if name not in (CLI, LAZY_EXPORTS)
           for imp, line, local in _imports(path)
           if local and imp.split(".")[0] == "mpa_gym"]
    assert not bad


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle of ``graph`` (as a path that returns to its start), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(u: str) -> list[str] | None:
        state[u] = 1
        stack.append(u)
        for v in sorted(graph.get(u, ())):
            if state.get(v) == 1:
                return [*stack[stack.index(v):], v]
            if v not in state and (found := visit(v)):
                return found
        state[u] = 2
        stack.pop()
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def _graph(prefix: str) -> dict[str, set[str]]:
    """Module -> the project modules it imports, function-local imports included."""
    graph: dict[str, set[str]] = {}
    for name, path in MODULES.items():
        if name.startswith(prefix):
            graph[name] = {imp for imp, _, _ in _imports(path)
                           if imp in MODULES and imp != name and imp.startswith(prefix)
                           and not name.startswith(imp + ".")}  # a module's own package
    return graph


@pytest.mark.parametrize("prefix", ["mpa_gym.agents", "mpa_gym"])
def test_no_import_cycle(prefix):
    assert _cycle(_graph(prefix)) is None


def test_the_cycle_finder_finds_a_cycle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


# docs/design.md#layers: each layer imports only from the layers above it
LAYERS = {"mpa_gym.files": 0, "mpa_gym.configs": 0, "mpa_gym.model": 1, "mpa_gym.design": 2,
          "mpa_gym.analysis": 3, "mpa_gym.task": 4, "mpa_gym.envs": 5, "mpa_gym.hardware": 5,
          "mpa_gym.figures": 6, "mpa_gym.bench": 6, "mpa_gym.agents": 7}


def _layer(module: str) -> int | None:
    hits = [rank for prefix, rank in LAYERS.items()
            if module == prefix or module.startswith(prefix + ".")]
    return max(hits) if hits else None


def test_each_library_layer_imports_only_from_the_layers_above_it():
    bad = []
    for name, path in MODULES.items():
        mine = _layer(name)
        for imp, line, _ in _imports(path):
            theirs = _layer(imp)
            if mine is not None and theirs is not None and theirs > mine:
                bad.append(f"{name}:{line} (layer {mine}) imports {imp} (layer {theirs})")
    assert not bad


def test_evaluating_and_loading_do_not_import_torch_until_a_model_is_read():
    # the report's modules are what the spawned workers and every `mpa-gym evaluate` import
    # first; torch (about 1 s to import) comes only with a learned model
    code = ("import sys, mpa_gym.agents.evaluation.evaluate, mpa_gym.agents.learned.policies, "
            "mpa_gym.agents.learned.runs; print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=ROOT)
    assert out.stdout.strip() == "False"
