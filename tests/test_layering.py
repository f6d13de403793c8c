"""The package layering of kpd6d, enforced on the source: every import in src/kpd6d, parsed with ``ast``
(module-level and function-level lazy ones, relative ones, ``importlib.import_module("kpd6d...")``
with a literal name), must follow the table below.

Layers, lowest first (a "unit" is a top-level module ``kpd6d/X.py`` or a subpackage ``kpd6d/X/``)::

    L0  io, geometry, registry, config, paths    file I/O, conventions, the registry tables, settings
    L1  objects, symmetry, render, pnp, visualize, pretrained, schedules, ema, finetune, box_errors
    L2  training, refinement                     the trainer/checkpoint/optimizer setup of both stages; pose refinement
    L3  keypoints
    L4  data, synth                              BOP datasets; the generator that writes them
    L5  evaluation, detection, kpd               metrics; the two trained stages
    L6  deploy                                   ONNX export of the stages; the torch-free runtime
    L7  pipeline, predict, benchmarks, workflow, tracking   stages put together
    L8  cli                                      Hydra entry points, imported by no library code

Rules:

* a unit may import any unit of a LOWER layer, never one of a higher layer;
* it may import another unit of its OWN layer only where ``SAME_LAYER`` lists that edge:
  ``config -> io`` (``to_plain`` lives with the file writers), ``paths -> config`` (the old home of
  ``config_dir``, a re-export, see ``MOVED``), ``synth -> data`` (the generator writes
  BOP files), ``kpd -> evaluation`` (the KPD's validation pose metrics), ``workflow -> pipeline``
  (``run_evaluation`` builds the pose pipeline), ``predict -> pipeline`` (prediction on images runs it),
  ``predict -> tracking`` (``kpd6d-predict track=true`` on a video / camera runs the tracker),
  ``benchmarks -> tracking`` (the pipeline benchmark times the tracker's box projection),
  ``benchmarks -> pipeline`` (the track benchmark runs the pose pipeline and the tracker on a video);
* there is no import cycle between units (checked on its own, so an allowance can never hide one);
* nothing outside ``kpd6d/cli`` imports ``kpd6d.cli``;
* ``kpd6d/__init__.py`` is the package's face and may re-export from any unit, but only lazily
  (inside functions, e.g. a module ``__getattr__``): ``import kpd6d.x`` runs it first, so a
  module-level import there would be an import of everything by everything. Library code may
  read ``kpd6d.__version__`` (``import kpd6d`` / ``from kpd6d import __version__``) and nothing else
  from the root;
* every unit must appear in the table (a new package gets a layer on purpose, not by default);
* a module renamed away keeps its old path only as a re-export for outside users (``MOVED``: old ->
  new); no library module imports an old path.
* ``kpd6d.deploy.runtime`` (the exported models' runtime) imports, at module level and through every
  kpd6d module it imports at module level, neither torch (nor kornia / Lightning / torchvision) nor
  ``kpd6d.kpd.module`` (tests/test_deploy.py also checks ``sys.modules`` after a prediction).

The registry's provider lists (``Registry("backbone", ("kpd6d.kpd.backbones",))``) are names imported
on first lookup, i.e. the plugin mechanism (providers register themselves into a lower-layer table);
they are data, not import statements, and are not edges here.
"""

from __future__ import annotations

import ast
import importlib
from collections import defaultdict
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "kpd6d"

LAYERS: list[tuple[str, ...]] = [
    ("io", "geometry", "registry", "config", "paths"),
    ("objects", "symmetry", "render", "pnp", "visualize", "pretrained", "schedules", "ema", "finetune",
     "box_errors", "distributed", "photo_augment"),
    ("training", "refinement"),
    ("keypoints",),
    ("data", "synth"),
    ("evaluation", "detection", "kpd"),
    ("deploy",),
    ("pipeline", "predict", "benchmarks", "workflow", "tracking"),
    ("cli",),
]
SAME_LAYER = {("config", "io"), ("paths", "config"), ("synth", "data"), ("kpd", "evaluation"),
              ("workflow", "pipeline"), ("predict", "pipeline"), ("predict", "tracking"),
              ("benchmarks", "tracking"), ("benchmarks", "pipeline")}
ROOT = ""  # the unit of kpd6d/__init__.py
ROOT_NAMES_ALLOWED = {"__version__"}
# old module path -> (where it moved, the names the old path still re-exports); kept because the docs
# named the old path
MOVED = {
    "kpd6d.kpd.select": ("kpd6d.pnp.top_l", ("solve_top_l", "top_l", "top_l_mask")),
    "kpd6d.paths": ("kpd6d.config", ("config_dir",)),
    "kpd6d.evaluation.evaluate": ("kpd6d.evaluation.runner", ("ADD_THRESHOLDS", "PX_THRESHOLDS", "compute_metrics",
                                                              "eval_instances", "evaluate", "match_predictions")),
    "kpd6d.detection.evaluate": ("kpd6d.detection.metrics", ("DetectionEvaluator", "evaluate_detector")),
}


def _module_name(path: Path, src: Path) -> str:
    parts = ("kpd6d", *path.relative_to(src).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _unit(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ROOT


def _is_module_level(node: ast.AST, parents: dict[ast.AST, ast.AST]) -> bool:
    p = parents.get(node)
    while p is not None:
        if isinstance(p, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            return False
        p = parents.get(p)
    return True


def scan_imports(src: Path = SRC) -> list[dict]:
    """Every kpd6d import in ``src``: ``{"file", "line", "module" (importer), "target" (imported
    module), "names" (for ``from X import a, b``), "module_level"}``."""
    found = []
    for path in sorted(src.rglob("*.py")):
        mod = _module_name(path, src)
        is_pkg = path.name == "__init__.py"
        tree = ast.parse(path.read_text(), filename=str(path))
        parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
        for node in ast.walk(tree):
            targets: list[tuple[str, tuple[str, ...]]] = []
            if isinstance(node, ast.Import):
                targets = [(a.name, ()) for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
                    base = base[: len(base) - (node.level - 1)]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                names = tuple(a.name for a in node.names)
                # ``from kpd6d.x import y`` may import the submodule kpd6d.x.y: same unit, so no matter
                targets = [(target, names)]
            elif (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)
                  and isinstance(node.args[0].value, str)
                  and ((isinstance(node.func, ast.Attribute) and node.func.attr == "import_module")
                       or (isinstance(node.func, ast.Name) and node.func.id in ("import_module", "__import__")))):
                targets = [(node.args[0].value, ())]
            for target, names in targets:
                if target == "kpd6d" or target.startswith("kpd6d."):
                    found.append({"file": str(path.relative_to(src.parent)), "line": node.lineno, "module": mod,
                                  "target": target, "names": names,
                                  "module_level": _is_module_level(node, parents)})
    return found


def layer_of(unit: str) -> int | None:
    for i, units in enumerate(LAYERS):
        if unit in units:
            return i
    return None


def units_in(src: Path = SRC) -> set[str]:
    return {p.stem if p.is_file() else p.name for p in src.iterdir()
            if (p.is_file() and p.suffix == ".py" and p.name != "__init__.py") or (p / "__init__.py").is_file()}


def violations(imports: list[dict], units: set[str]) -> list[str]:
    """Every breach of the rules in this module's docstring, one readable line each."""
    out = [f"kpd6d.{u}: not in the layer table of tests/test_layering.py" for u in sorted(units)
           if layer_of(u) is None]
    for imp in imports:
        src_u, dst_u = _unit(imp["module"]), _unit(imp["target"])
        where = f"{imp['file']}:{imp['line']}: {imp['module']} imports {imp['target']}"
        if dst_u == "cli" and src_u != "cli":
            out.append(f"{where} -- the library never imports kpd6d.cli")
            continue
        if src_u == ROOT:
            if imp["module_level"] and dst_u != ROOT:
                out.append(f"{where} -- kpd6d/__init__.py may re-export only lazily (inside a function)")
            continue
        if dst_u == ROOT:
            extra = set(imp["names"]) - ROOT_NAMES_ALLOWED
            if extra:
                out.append(f"{where} -- from the package root only {sorted(ROOT_NAMES_ALLOWED)}, not {sorted(extra)}")
            continue
        if src_u == dst_u:
            continue
        ls, ld = layer_of(src_u), layer_of(dst_u)
        if ls is None or ld is None:
            continue  # reported above
        if ld > ls:
            out.append(f"{where} -- L{ls} {src_u} may not import the higher layer L{ld} {dst_u}")
        elif ld == ls and (src_u, dst_u) not in SAME_LAYER:
            out.append(f"{where} -- {src_u} and {dst_u} are both L{ls}; a same-layer import needs a SAME_LAYER entry")
    return out


def unit_graph(imports: list[dict]) -> dict[str, set[str]]:
    g: dict[str, set[str]] = defaultdict(set)
    for imp in imports:
        a, b = _unit(imp["module"]), _unit(imp["target"])
        if a != b and ROOT not in (a, b):  # the root's lazy re-exports are checked above
            g[a].add(b)
    return g


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle between units (``[a, b, ..., a]``), or None."""
    state: dict[str, int] = {}  # 1 on the stack, 2 done
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if state.get(m) == 1:
                return [*stack[stack.index(m):], m]
            if m not in state and (c := visit(m)):
                return c
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state and (c := visit(n)):
            return c
    return None


# ---------------------------------------------------------------------------------------------
# the rules on kpd6d itself
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def imports() -> list[dict]:
    found = scan_imports()
    assert len({i["module"] for i in found}) > 50, "the scan found too few importing modules; is SRC right?"
    return found


def test_layering(imports):
    bad = violations(imports, units_in())
    assert not bad, "layering broken:\n" + "\n".join(bad)


def test_no_import_cycle_between_packages(imports):
    cycle = find_cycle(unit_graph(imports))
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_library_never_imports_cli(imports):
    bad = [f"{i['file']}:{i['line']}" for i in imports
           if _unit(i["target"]) == "cli" and _unit(i["module"]) != "cli"]
    assert not bad, "kpd6d.cli imported from the library at " + ", ".join(bad)


def test_library_never_imports_a_moved_module(imports):
    bad = [f"{i['file']}:{i['line']}: {old} (now {MOVED[old][0]})" for i in imports
           for old in (i["target"], *(f"{i['target']}.{n}" for n in i["names"]))
           if old in MOVED and i["module"] not in MOVED]
    assert not bad, "old module paths imported by the library:\n" + "\n".join(bad)


@pytest.mark.parametrize("old", sorted(MOVED))
def test_moved_module_reexports_the_new_one(old):
    new, names = MOVED[old]
    before, after = importlib.import_module(old), importlib.import_module(new)
    assert all(getattr(before, n) is getattr(after, n) for n in names)


def test_io_is_a_leaf(imports):
    assert not [i for i in imports if i["module"] == "kpd6d.io"], "kpd6d.io imports no other kpd6d module"


TORCH_PACKAGES = ("torch", "torchvision", "kornia", "pytorch_lightning", "lightning", "timm")


def module_level_closure(start: str, src: Path = SRC) -> tuple[set[str], set[str]]:
    """(kpd6d modules, third-party top-level packages) that ``import start`` imports at module level,
    following kpd6d modules (and the packages above them) transitively."""
    seen: set[str] = set()
    third: set[str] = set()
    todo = [start]
    while todo:
        mod = todo.pop()
        if mod in seen:
            continue
        seen.add(mod)
        parts = mod.split(".")
        todo += [".".join(parts[:i]) for i in range(1, len(parts))]  # parent packages run first
        rel = Path(*parts[1:]) if len(parts) > 1 else Path()
        path = src / rel / "__init__.py" if (src / rel / "__init__.py").is_file() else src / rel.with_suffix(".py")
        if not path.is_file():
            continue
        tree = ast.parse(path.read_text())
        parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(tree):
            if not isinstance(node, (ast.Import, ast.ImportFrom)) or not _is_module_level(node, parents):
                continue
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif node.level:
                base = parts if is_pkg else parts[:-1]
                base = base[: len(base) - (node.level - 1)]
                names = [".".join(base + ([node.module] if node.module else []))]
            else:
                names = [node.module or ""]
                if node.module and node.module.startswith("kpd6d"):  # from kpd6d.x import submodule
                    names += [f"{node.module}.{a.name}" for a in node.names
                              if (src / Path(*node.module.split(".")[1:]) / f"{a.name}.py").is_file()]
            for n in names:
                if n == "kpd6d" or n.startswith("kpd6d."):
                    todo.append(n)
                elif n and n != "__future__":
                    third.add(n.split(".")[0])
    return seen, third


def test_deploy_runtime_imports_no_torch_and_no_kpd_module():
    mods, third = module_level_closure("kpd6d.deploy.runtime")
    assert {"kpd6d.kpd.decoders_numpy", "kpd6d.geometry", "kpd6d.deploy.ops"} <= mods  # the closure is followed
    assert not set(third) & set(TORCH_PACKAGES), f"kpd6d.deploy.runtime imports {sorted(set(third) & set(TORCH_PACKAGES))}"
    assert "kpd6d.kpd.module" not in mods
    # and the check can fail: the export module imports torch
    assert "torch" in module_level_closure("kpd6d.deploy.export")[1]


# ---------------------------------------------------------------------------------------------
# the checker finds what it must (a fake package tree)
# ---------------------------------------------------------------------------------------------
def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    src = tmp_path / "kpd6d"
    for rel, text in files.items():
        p = src / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return src


def test_checker_catches_upward_same_layer_cli_root_and_cycles(tmp_path):
    src = _tree(tmp_path, {
        "__init__.py": "from kpd6d.data import BopDataset\n",
        "io.py": "",
        "geometry.py": "def f():\n    from kpd6d.kpd import module\n",       # lazy upward import
        "objects/__init__.py": "from . import model\n",
        "objects/model.py": "from ..render import Renderer\n",                    # same layer, not listed
        "render.py": "import importlib\nimportlib.import_module('kpd6d.objects.model')\n",
        "data/__init__.py": "from kpd6d import BopDataset\n",                    # root name other than __version__
        "kpd/__init__.py": "",
        "kpd/module.py": "import kpd6d.cli.train\n",
        "synth/__init__.py": "import kpd6d\nfrom kpd6d import __version__\n",   # allowed
        "mystery.py": "",
    })
    found = scan_imports(src)
    bad = violations(found, units_in(src))
    text = "\n".join(bad)
    assert "kpd6d.mystery: not in the layer table" in text
    assert "kpd6d/__init__.py:1: kpd6d imports kpd6d.data -- kpd6d/__init__.py may re-export only lazily" in text
    assert "kpd6d/geometry.py:2: kpd6d.geometry imports kpd6d.kpd -- L0 geometry may not import the higher layer L5 kpd" in text
    assert "kpd6d/objects/model.py:1: kpd6d.objects.model imports kpd6d.render -- objects and render are both L1" in text
    assert "kpd6d/render.py:2: kpd6d.render imports kpd6d.objects.model" in text
    assert "kpd6d/data/__init__.py:1: kpd6d.data imports kpd6d -- from the package root only" in text
    assert "kpd6d/kpd/module.py:1: kpd6d.kpd.module imports kpd6d.cli.train -- the library never imports kpd6d.cli" in text
    assert "synth" not in text
    assert len(bad) == 7
    assert find_cycle(unit_graph(found)) == ["objects", "render", "objects"]


def test_checker_passes_a_clean_tree(tmp_path):
    src = _tree(tmp_path, {
        "__init__.py": "def __getattr__(name):\n    from kpd6d.data import BopDataset\n    return BopDataset\n",
        "io.py": "",
        "config.py": "from kpd6d.io import to_plain\n",
        "data/__init__.py": "from .reader import BopDataset\n",
        "data/reader.py": "from kpd6d.io import read_json\n",
        "cli/__init__.py": "from kpd6d.data import BopDataset\n",
    })
    found = scan_imports(src)
    assert {(i["module"], i["target"]) for i in found} == {
        ("kpd6d", "kpd6d.data"), ("kpd6d.config", "kpd6d.io"), ("kpd6d.data", "kpd6d.data.reader"),
        ("kpd6d.data.reader", "kpd6d.io"), ("kpd6d.cli", "kpd6d.data")}
    assert violations(found, units_in(src)) == []
    assert find_cycle(unit_graph(found)) is None
