"""The layers import only downward: core <- transports (the transports' protocol code, the runtime,
the ``coex`` facade, the conformance kit) <- modalities (the built-in plugins, the sample plugin)
<- apps (console, demo, vehicle); inside the transports layer the protocol code imports neither the
runtime nor the facade, and the runtime does not import the facade; the conformance kit imports
only ``coex`` and itself, the plugins only ``coex`` (and the kit) and their own package; no module
imports itself back through others (no cycles); README and docs show only the public facade for
core and run-loop names."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: import package -> where it lives in the repository
PACKAGES = {
    "coex_core": "coex_core",
    "coex_transports": "transports/coex_transports",
    "coex_runtime": "runtime/coex_runtime",
    "coex": "coex",
    "coex_conformance": "conformance_tests/coex_conformance",
    "coex_plugins": "plugins/coex_plugins",
    "coex_sample_plugin": "examples/coex-sample-plugin/coex_sample_plugin",
    "coex_apps": "apps/coex_apps",
}
LAYER_NAMES = ("core", "transports", "modalities", "apps")
#: the transports layer from the bottom: protocol code, runtime, facade, conformance kit
TIERS = ("coex_transports", "coex_runtime", "coex", "coex_conformance")
#: packages that import only the facade ``coex`` and themselves (and libraries that are not CoEx):
#: the conformance kit, shipped to third parties, and the plugins, which may also use the kit (a
#: plugin's conformance companion is written with it)
ONLY_THE_FACADE = {
    "coex_conformance": ("coex",),
    "coex_plugins": ("coex", "coex_conformance"),
    "coex_sample_plugin": ("coex", "coex_conformance"),
}
#: imports inside the transports layer that go up a tier, each with why it is still there; an
#: entry no longer needed fails the test (delete it)
KNOWN_TIER_IMPORTS = {
    ("coex_transports.micromodem.simnetwork", "coex_runtime.runner"):
        "SimLoop (runners over simulated modems) uses the runner's next_wakeup: a run loop, not "
        "protocol code, to join the runtime's loops",
}


def layer(module: str) -> int:
    """0 core, 1 transports (protocol code, runtime, facade, conformance kit), 2 modalities,
    3 apps."""
    top = module.split(".")[0]
    if top == "coex_core":
        return 0
    if top in TIERS:
        return 1
    if top == "coex_apps":
        return 3
    return 2


def modules(root: Path) -> dict[str, Path]:
    out: dict[str, Path] = {}
    for pkg, where in PACKAGES.items():
        base = root / where
        for path in base.rglob("*.py"):
            if "_types" in path.relative_to(base).parts:  # lcm-gen output
                continue
            parts = [pkg, *path.relative_to(base).with_suffix("").parts]
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = path
    return out


#: registry calls that name the plugin they load: ``load_modality("bathymetry")`` imports the
#: module registered under that name as surely as an import statement does
REGISTRY_LOOKUPS = {"load_modality": "coex.modalities", "load_transport": "coex.transports"}


def registered(root: Path) -> dict[tuple[str, str], str]:
    """(entry-point group, name) -> the module it points at, from ``pyproject.toml``."""
    path = root / "pyproject.toml"
    if not path.exists():
        return {}
    groups = tomllib.loads(path.read_text()).get("project", {}).get("entry-points", {})
    return {(group, name): target.split(":")[0].strip()
            for group, eps in groups.items() for name, target in eps.items()}


def _constant(node: ast.AST) -> str | None:
    return node.value if isinstance(node, ast.Constant) and isinstance(node.value, str) else None


def imports_of(name: str, path: Path, known: dict[str, Path],
               entry: dict[tuple[str, str], str] | None = None) -> set[str]:
    """Every project module ``name`` imports, at any depth of the file (lazy imports count), and
    every module it loads by name: ``import_module("pkg.mod")`` and the registry's
    ``load_modality("name")`` / ``load_transport("name")`` / ``load(group, "name")``."""
    found: set[str] = set()
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call):
            func = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            args = [_constant(a) for a in node.args]
            if func == "import_module" and args and args[0]:
                found.add(args[0])
            elif func in REGISTRY_LOOKUPS and args and args[0]:
                found.add((entry or {}).get((REGISTRY_LOOKUPS[func], args[0]), ""))
            elif func == "load" and len(args) >= 2 and args[0] and args[1]:
                found.add((entry or {}).get((args[0], args[1]), ""))
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            found.add(mod)
            found.update(f"{mod}.{a.name}" for a in node.names if f"{mod}.{a.name}" in known)
    out: set[str] = set()
    for mod in found:
        parts = mod.split(".")
        while parts and ".".join(parts) not in known:
            parts.pop()
        if parts:
            out.add(".".join(parts))
    out.discard(name)
    return out


def graph(root: Path) -> dict[str, set[str]]:
    known = modules(root)
    entry = registered(root)
    return {name: imports_of(name, path, known, entry) for name, path in known.items()}


def upward(g: dict[str, set[str]]) -> list[str]:
    return [f"{a} ({LAYER_NAMES[layer(a)]}) imports {b} ({LAYER_NAMES[layer(b)]})"
            for a, deps in sorted(g.items()) for b in sorted(deps) if layer(b) > layer(a)]


def cycles(g: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected groups of modules (a package importing its own submodules, or a
    submodule its package, is not a cycle)."""
    def edges(n: str) -> list[str]:
        return [d for d in g[n] if not d.startswith(n + ".") and not n.startswith(d + ".")]

    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges(v):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                found.append(sorted(group))

    for v in sorted(g):
        if v not in index:
            visit(v)
    return found


def up_a_tier(g: dict[str, set[str]]) -> list[str]:
    """Imports inside the transports layer from a lower tier to a higher one (protocol code
    importing the runtime or the facade, the runtime importing the facade, anything below the
    conformance kit importing it)."""
    def tier(m: str) -> int:
        return TIERS.index(m.split(".")[0])

    return [f"{a} imports {b}" for a, deps in sorted(g.items()) if layer(a) == 1
            for b in sorted(deps) if layer(b) == 1 and tier(b) > tier(a)]


def beside_the_facade(g: dict[str, set[str]]) -> list[str]:
    """Imports of a module of the conformance kit or of a plugin package that are neither
    ``coex`` (nor, for a plugin, the conformance kit) nor its own package."""
    return [f"{a} imports {b}" for a, deps in sorted(g.items()) if a.split(".")[0] in ONLY_THE_FACADE
            for b in sorted(deps)
            if b.split(".")[0] not in (*ONLY_THE_FACADE[a.split(".")[0]], a.split(".")[0])]


def test_no_layer_imports_a_layer_above_it() -> None:
    assert upward(graph(ROOT)) == []


def test_protocol_code_imports_neither_runtime_nor_facade() -> None:
    found = up_a_tier(graph(ROOT))
    known = [f"{a} imports {b}" for a, b in KNOWN_TIER_IMPORTS]
    assert [f for f in found if f not in known] == []
    assert [k for k in known if k not in found] == [], "no longer imported: delete from KNOWN_TIER_IMPORTS"


def test_the_kit_and_the_plugins_import_only_the_facade_and_themselves() -> None:
    """The conformance kit (shipped to third parties), the built-in plugins and the sample
    third-party plugin import ``coex`` (the plugins also the kit) and their own package only."""
    found = beside_the_facade(graph(ROOT))
    assert found == []
    assert {m.split(".")[0] for m in modules(ROOT)} >= set(ONLY_THE_FACADE)


def test_no_module_imports_itself_back_through_others() -> None:
    assert cycles(graph(ROOT)) == []


def private_imports(g: dict[str, set[str]]) -> list[str]:
    """Imports of another package's private module (``coex_core._wire``,
    ``coex_plugins.bathymetry._codec`` from outside ``coex_plugins.bathymetry``)."""
    out = []
    for a, deps in sorted(g.items()):
        for b in sorted(deps):
            parts = b.split(".")
            for i, part in enumerate(parts):
                owner = ".".join(parts[:i])
                if part.startswith("_") and not part.startswith("__"):
                    if not (a == owner or a.startswith(owner + ".")):
                        out.append(f"{a} imports {b}")
                    break  # inside its owner, a private module may use its own private parts
    return out


def test_no_module_reaches_into_another_package_s_private_modules() -> None:
    assert private_imports(graph(ROOT)) == []


def test_the_checks_catch_an_upward_import_and_a_cycle(tmp_path: Path) -> None:
    """The checks above on a made-up tree: a transport importing a plugin, two console modules
    importing each other (lazily, inside a function), a plugin using a core private module and
    the core beside the facade, protocol code using the runtime, the runtime the facade."""
    for where in PACKAGES.values():
        (tmp_path / where).mkdir(parents=True, exist_ok=True)
        (tmp_path / where / "__init__.py").write_text("")
    (tmp_path / "coex_core" / "wire.py").write_text("X = 1\n")
    (tmp_path / "transports/coex_transports/lcm.py").write_text(
        "def f():\n    from coex_plugins.bathymetry import decode\n")
    (tmp_path / "coex_core" / "_codec.py").write_text("from . import wire\n")
    (tmp_path / "plugins/coex_plugins/bathymetry.py").write_text(
        "import numpy\nimport coex\nfrom coex.messages import Subgrid\nfrom coex_core import wire\n"
        "from coex_core._codec import X\nfrom . import render\n")
    (tmp_path / "plugins/coex_plugins/render.py").write_text("from coex_runtime import runner\n")
    console = tmp_path / "apps/coex_apps/console"
    console.mkdir()
    (console / "__init__.py").write_text("")
    (console / "node.py").write_text("def attach():\n    from .server import Hub\n")
    (console / "server.py").write_text("from .node import attach\nfrom coex_core import wire\n")
    (tmp_path / "runtime/coex_runtime/runner.py").write_text("from coex_core import wire\n")
    (tmp_path / "runtime/coex_runtime/store.py").write_text("import coex\n")
    (tmp_path / "transports/coex_transports/sim.py").write_text(
        "def run():\n    from coex_runtime.runner import next_wakeup\n")
    (tmp_path / "examples/coex-sample-plugin/coex_sample_plugin/dark.py").write_text(
        "from coex import Modality\nfrom coex_sample_plugin import X\nfrom coex_plugins import render\n"
        "from coex_conformance import companions\n")
    # the kit: the facade and itself, not the core or the runtime behind the facade
    kit = tmp_path / "conformance_tests/coex_conformance"
    (kit / "companions.py").write_text("from coex import Modality\nfrom coex.messages import Opaque\n")
    (kit / "noderun.py").write_text(
        "from .companions import X\nfrom coex_core import wire\n\ndef f():\n    from coex_runtime import runner\n")
    # links the wrong way without an import statement: a module named in a string, a plugin
    # loaded by its registered name
    (tmp_path / "coex_core" / "cli.py").write_text(
        "import importlib\ndef f():\n    return importlib.import_module('coex_apps.console.node')\n")
    (tmp_path / "transports/coex_transports/products.py").write_text(
        "from coex_core.registry import load_modality\nDECODE = load_modality('bathymetry').decode\n")
    (tmp_path / "pyproject.toml").write_text(
        '[project.entry-points."coex.modalities"]\nbathymetry = "coex_plugins.bathymetry:Modality [x]"\n')
    g = graph(tmp_path)
    assert upward(g) == ["coex_core.cli (core) imports coex_apps.console.node (apps)",
                         "coex_transports.lcm (transports) imports coex_plugins.bathymetry (modalities)",
                         "coex_transports.products (transports) imports coex_plugins.bathymetry "
                         "(modalities)"]
    assert cycles(g) == [["coex_apps.console.node", "coex_apps.console.server"]]
    assert private_imports(g) == ["coex_plugins.bathymetry imports coex_core._codec"]
    assert up_a_tier(g) == ["coex_runtime.store imports coex",
                            "coex_transports.sim imports coex_runtime.runner"]
    assert beside_the_facade(g) == ["coex_conformance.noderun imports coex_core",
                                    "coex_conformance.noderun imports coex_core.wire",
                                    "coex_conformance.noderun imports coex_runtime",
                                    "coex_conformance.noderun imports coex_runtime.runner",
                                    "coex_plugins.bathymetry imports coex_core",
                                    "coex_plugins.bathymetry imports coex_core._codec",
                                    "coex_plugins.bathymetry imports coex_core.wire",
                                    "coex_plugins.render imports coex_runtime",
                                    "coex_plugins.render imports coex_runtime.runner",
                                    "coex_sample_plugin.dark imports coex_plugins",
                                    "coex_sample_plugin.dark imports coex_plugins.render"]


DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
#: core modules and the runtime (run loops, store) are imported from the facade; a plugin's or a
#: transport plugin's own API (``coex_plugins.bathymetry``, ``coex_transports.lcm``) from its package
PRIVATE = re.compile(r"^\s*(from|import)\s+(coex_core\b|coex_runtime\b|coex_transports\._\w+\b)")


@pytest.mark.parametrize("doc", DOCS, ids=[p.name for p in DOCS])
def test_docs_import_core_names_only_from_the_public_facade(doc: Path) -> None:
    bad = []
    in_code = False
    for n, line in enumerate(doc.read_text().splitlines(), 1):
        if line.lstrip().startswith("```"):
            in_code = not in_code
        elif in_code and PRIVATE.match(line):
            bad.append(f"{doc.name}:{n}: {line.strip()}")
    assert bad == []


def test_the_facade_offers_what_integrators_and_plugin_authors_need() -> None:
    import coex
    from coex_core.modality import ModalitySender
    from coex_core.storage import Storage
    from coex_runtime.runner import Runner

    names = {"Node", "ChannelManager", "LinkConfig", "Schedule", "StreamConfig", "Modality",
             "ModalitySender", "ModalityReceiver", "Transport", "Product", "open_transport",
             "Runner", "SimNetwork", "NodeStore", "CoexError", "ConfigError", "DecodeError",
             # plugin, input and autonomy authors
             "Storage", "MemoryStorage", "Input", "InputContext", "Item", "Autonomy", "SurveyPlan",
             "SurveyReport", "Detector", "Finding", "persistent", "StateError", "merged_config",
             "Problems", "RequestTracker", "to_stamp", "unwrap", "STAMP_MODULUS", "encode_subgrid",
             "decode_subgrid"}
    assert names <= set(coex.__all__)
    assert all(getattr(coex, n) is not None for n in coex.__all__)
    assert coex.Runner is Runner and coex.ModalitySender is ModalitySender and coex.Storage is Storage
    from coex.messages import Opaque  # the facade's modules (files re-exporting the core's names)
    from coex.tracker import State

    assert Opaque is coex.messages.Opaque and State is coex.tracker.State


def test_importing_the_facade_loads_no_plugin_app_or_middleware() -> None:
    code = ("import sys, coex; print(sorted(m for m in sys.modules if m.startswith(('coex_plugins', "
            "'coex_apps', 'coex_conformance', 'coex.lcm', 'coex.moos', 'coex.ros', 'coex_transports.lcm', "
            "'coex_transports.moos', 'coex_transports.ros', 'coex_transports.mavlink', "
            "'coex_transports.micromodem'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
