"""The floors of ARCHITECTURE.md, checked on the source (ast, through the run store's import walk;
nothing is imported): a module imports only
its own floor or lower ones (floor 1 nothing of the project but a sibling in bench/nn, bench/errors and
bench/atomic),
with no import cycles; models never import data loading or the run store; metrics and losses never
import models; the tools beside the experiments (predict, tracking) import nothing of them; one factory
builds models. The floors are read from ARCHITECTURE.md's table, so the document and the test cannot
drift apart."""
import re
from pathlib import Path

import pytest

from bench import runs

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("bench", "baselines")


def _floors() -> dict[str, int]:
    """path prefix ('bench/nn/', 'bench/metrics.py', ...) -> floor number, from ARCHITECTURE.md."""
    floors = {}
    for line in (ROOT / "ARCHITECTURE.md").read_text().splitlines():
        match = re.match(r"\|\s*(\d)\s[^|]*\|([^|]*)\|", line)
        if match:
            for path in re.findall(r"`((?:bench|baselines)/[\w/.]*)`", match.group(2)):
                floors[path] = int(match.group(1))
    return floors


FLOORS = _floors()
SOURCES = sorted(p.relative_to(ROOT).as_posix() for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))


def floor_of(path: str) -> int | None:
    matches = [prefix for prefix in FLOORS if path == prefix or (prefix.endswith("/") and path.startswith(prefix))]
    return FLOORS[max(matches, key=len)] if matches else None


def project_imports(path: str) -> set[str]:
    """Project source files `path` imports (the run store's import walk, which code identity uses too;
    `from x import y` where y is a module counts as x.y); package __init__ files are left out."""
    name = ".".join(Path(path).with_suffix("").parts).removesuffix(".__init__")
    found = set()
    for imported in runs.project_imports(ROOT / path, name):
        target = runs.module_file(imported)
        if target is not None:
            relative = target.relative_to(ROOT).as_posix()
            if relative != path and not relative.endswith("__init__.py"):
                found.add(relative)
    return found


def test_every_source_file_has_a_floor():
    assert [p for p in SOURCES if not p.endswith("__init__.py") and floor_of(p) is None] == []


@pytest.mark.parametrize("path", [p for p in SOURCES if not p.endswith("__init__.py")])
def test_imports_go_down_the_floors(path):
    mine = floor_of(path)
    for target in project_imports(path):
        theirs = floor_of(target)
        if mine == 1:
            allowed = target in ("bench/errors.py", "bench/atomic.py") or (path.startswith("bench/nn/") and target.startswith("bench/nn/"))
            assert allowed, f"{path} (floor 1) imports {target}"
        else:
            assert theirs <= mine, f"{path} (floor {mine}) imports {target} (floor {theirs})"


def test_no_import_cycles():
    graph = {p: project_imports(p) for p in SOURCES}
    state = {}

    def visit(node, trail):
        state[node] = "open"
        for nxt in graph.get(node, ()):
            assert state.get(nxt) != "open", "import cycle: " + " -> ".join(trail + [nxt])
            if nxt not in state:
                visit(nxt, trail + [nxt])
        state[node] = "done"
    for node in graph:
        if node not in state:
            visit(node, [node])


def test_models_never_import_data_loading_or_the_run_store_and_metrics_never_import_models():
    forbidden_for_models = {"bench/dataset.py", "bench/datagen.py", "bench/runs.py", "bench/render.py"}
    for path in SOURCES:
        imports = project_imports(path)
        if path.startswith(("bench/models/", "baselines/")):
            assert not imports & forbidden_for_models, f"{path} imports {imports & forbidden_for_models}"
        if path in ("bench/metrics.py", "bench/losses.py"):
            assert not [t for t in imports if t.startswith(("bench/models/", "baselines/"))], path


def test_the_tools_beside_the_experiments_import_nothing_of_them():
    """predict and tracking share floor 3 with the experiments without loading them: the standalone
    predictor needs a model factory and a weights file, not the tables' pipeline."""
    tools = [p for p, floor in FLOORS.items() if floor == 3 and not p.startswith("bench/experiments/")]
    assert {"bench/predict.py", "bench/tracking.py"} <= set(tools)
    for path in tools:
        assert not [t for t in project_imports(path) if t.startswith("bench/experiments/")], path


def test_one_factory_builds_models():
    """`hydra.utils.instantiate` is called in one place, bench/models/factory.py (ARCHITECTURE.md)."""
    callers = [p for p in SOURCES if re.search(r"\binstantiate\(", (ROOT / p).read_text())]
    assert callers == ["bench/models/factory.py"]


def test_the_floor_table_is_read():
    assert FLOORS["bench/runs.py"] == 1 and FLOORS["bench/experiments/"] == 3 and FLOORS["bench/cli.py"] == 4
    assert FLOORS["bench/models/"] == 2 and FLOORS["bench/weights.py"] == 2 and FLOORS["bench/predict.py"] == 3


def test_only_the_cli_and_the_model_factory_import_hydra():
    importers = [p for p in SOURCES if re.search(r"^\s*(import hydra|from hydra\b)", (ROOT / p).read_text(), re.M)]
    assert importers == ["bench/cli.py", "bench/models/factory.py"]


def test_the_typed_settings_have_no_defaults_and_the_config_sets_exactly_their_fields():
    """Recipe, EvalSpec and VggSpec take every value from conf/config.yaml (`train:`, `eval:`, `vgg:`):
    one source of truth, no second default in code."""
    import dataclasses
    from omegaconf import OmegaConf
    from bench.experiments.context import EvalSpec, VggSpec
    from bench.train import Recipe
    config = OmegaConf.load(ROOT / "conf/config.yaml")
    for spec, section in ((Recipe, "train"), (EvalSpec, "eval"), (VggSpec, "vgg")):
        fields = dataclasses.fields(spec)
        assert [f.name for f in fields if f.default is not dataclasses.MISSING
                or f.default_factory is not dataclasses.MISSING] == [], spec.__name__
        assert set(config[section]) == {f.name for f in fields}, section


def test_the_models_that_apply_the_hdr_transform_are_the_ones_architecture_names():
    """ARCHITECTURE.md: the trainer and evaluator apply the HDR transform; only the models it names
    (those that take `linear_base`) import bench/hdr.py."""
    text = (ROOT / "ARCHITECTURE.md").read_text()
    paragraph = text[text.index("One exception,\ninside the models"):text.index("no other\nmodel imports it")]
    named = set(re.findall(r"`((?:bench/models|baselines)/[\w/]+\.py)`", paragraph))
    importers = {p for p in SOURCES if p.startswith(("bench/models/", "baselines/"))
                 and "bench/hdr.py" in project_imports(p)}
    assert named and importers == named
