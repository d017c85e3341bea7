"""The layout's one rule, checked on the import graph: engine <- protocol <- server; the client needs only the
protocol (and the BV encoder); io and lab may use anything. Function-level (lazy) imports count too."""

from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"bb_align": ROOT / "service" / "bb_align", "bb_align_client": ROOT / "client" / "bb_align_client"}
# What the protocol and the client may take from the engine: the BV image encoder, its config, box rows, SE(2/3),
# the sweep de-skew.
ENGINE_PUBLIC = {
    "bb_align.engine",
    "bb_align.engine.bev",
    "bb_align.engine.config",
    "bb_align.engine.geometry",
    "bb_align.engine.boxes",
    "bb_align.engine.deskew",  # a sender's sweep de-skew (bb_align_client.deskew re-exports it)
}

# area -> (areas it may import, extra modules it may import)
RULES = {
    "engine": ({"engine"}, set()),
    "protocol": ({"protocol"}, ENGINE_PUBLIC),
    "server": ({"engine", "protocol", "server"}, set()),
    "client": ({"client", "protocol"}, ENGINE_PUBLIC),
    "io": ({"engine", "protocol", "io"}, set()),
    "lab": ({"engine", "protocol", "server", "io", "lab", "client"}, set()),
    "cli": ({"engine", "protocol", "server", "io", "lab", "client", "cli"}, set()),
    "root": ({"engine"}, set()),  # bb_align/__init__.py re-exports the engine (lazily)
}


def area(module: str) -> str:
    parts = module.split(".")
    if parts[0] == "bb_align_client":
        return "client"
    if len(parts) == 1:
        return "root"
    return {"__main__": "cli"}.get(parts[1], parts[1])


def modules() -> dict[str, Path]:
    out = {}
    for pkg, base in PACKAGES.items():
        for path in base.rglob("*.py"):
            rel = path.relative_to(base).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            out[".".join([pkg, *parts])] = path
    return out


def imports_of(module: str, path: Path) -> set[str]:
    """Every bb_align / bb_align_client module this file imports, anywhere in it (relative ones resolved)."""
    is_pkg = path.name == "__init__.py"
    here = module.split(".") if is_pkg else module.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = here[: len(here) - (node.level - 1)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            found.add(name)
            # `from pkg import submodule`
            found.update(f"{name}.{a.name}" for a in node.names if f"{name}.{a.name}" in MODULES)
    return {m for m in found if m.split(".")[0] in PACKAGES}


MODULES = modules()


def test_every_import_points_the_allowed_way():
    bad = []
    for module, path in sorted(MODULES.items()):
        allowed_areas, allowed_modules = RULES[area(module)]
        for target in sorted(imports_of(module, path)):
            if target in allowed_modules or area(target) in allowed_areas | {"root"}:  # `bb_align` is __version__
                continue
            bad.append(f"{module} imports {target}")
    assert not bad, "imports against the layout's direction:\n" + "\n".join(bad)


def test_the_rule_checker_catches_a_client_importing_the_server(tmp_path):
    """The check above is not vacuous: a client module importing the server is flagged."""
    path = tmp_path / "rest.py"
    path.write_text("from bb_align.server.settings import Settings\n")
    targets = imports_of("bb_align_client.rest", path)
    allowed_areas, allowed_modules = RULES["client"]
    assert targets == {"bb_align.server.settings"}
    assert not all(t in allowed_modules or area(t) in allowed_areas for t in targets)


def _loaded_after(statement: str) -> list[str]:
    code = f"import sys\n{statement}\nimport json\nprint(json.dumps(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


HEAVY = ("fastapi", "uvicorn", "zenoh", "starlette", "prometheus_client")


@pytest.mark.parametrize(
    "statement",
    [
        "import bb_align_client",
        "from bb_align_client import AlignClient, encode_frame",
        "import bb_align.protocol",
    ],
)
def test_senders_load_no_server_and_no_zenoh(statement):
    loaded = _loaded_after(statement)
    bad = [
        m
        for m in loaded
        if m.split(".")[0] in HEAVY
        or m.startswith(("bb_align.server", "bb_align.lab"))
        or m == "bb_align.engine.pipeline"
    ]
    assert not bad, bad


def test_the_engine_loads_no_server_network_or_lab_package():
    loaded = _loaded_after("import bb_align.engine as e\ne.Aligner\ne.align_clouds")
    assert not [m for m in loaded if m.split(".")[0] in HEAVY + ("msgpack", "httpx", "typer", "matplotlib")]
    assert not [
        m for m in loaded if m.startswith(("bb_align.protocol", "bb_align.server", "bb_align.lab", "bb_align.io"))
    ]


def test_the_engine_imports_only_the_engine_extra():
    """Every third-party package the engine's files import belongs to a distribution of the `engine` extra in
    pyproject.toml: the numpy-only install path documented there is complete."""
    import importlib.metadata as md

    extra = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]["engine"]
    norm = lambda name: re.sub(r"[-_.]+", "-", name).lower()
    allowed = {norm(re.split(r"[<>=!~ \[]", d)[0]) for d in extra}
    top_to_dist = md.packages_distributions()
    tops = set()
    for path in (PACKAGES["bb_align"] / "engine").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                tops.update(a.name.split(".")[0] for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                tops.add(node.module.split(".")[0])
    third_party = tops - set(sys.stdlib_module_names) - set(PACKAGES) - {"__future__"}
    assert third_party, "no third-party import found: the scan is broken"
    outside = {
        top: top_to_dist.get(top) for top in third_party if not {norm(d) for d in top_to_dist.get(top, [top])} & allowed
    }
    assert not outside, f"the engine imports packages outside the `engine` extra: {outside}"


MAX_FUNCTION_LINES = 60
PRODUCT_ROOMS = [
    *(PACKAGES["bb_align"] / room for room in ("engine", "protocol", "server", "io")),
    PACKAGES["bb_align_client"],
]


def long_functions(path: Path, limit: int = MAX_FUNCTION_LINES) -> list[str]:
    """Every function (nested ones and methods too) of the file longer than ``limit`` lines, counted from its
    ``def`` line to its last line."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            lines = node.end_lineno - node.lineno + 1
            if lines > limit:
                out.append(f"{path}:{node.lineno} {node.name} ({lines} lines)")
    return out


def test_no_function_in_the_product_rooms_is_over_60_lines():
    bad = [f for room in PRODUCT_ROOMS for path in sorted(room.rglob("*.py")) for f in long_functions(path)]
    assert not bad, "functions over 60 lines:\n" + "\n".join(bad)


def test_the_length_check_counts_def_to_end(tmp_path):
    """The check above is not vacuous: a method of 61 lines is flagged, a function of 60 lines is not."""
    statements = [f"x{i} = {i}" for i in range(59)]
    fits = "def fits():\n" + "".join(f"    {st}\n" for st in statements)  # def + 59 lines
    over = "class C:\n    def over(self):\n" + "".join(f"        {st}\n" for st in [*statements, "y = 1"])
    path = tmp_path / "probe.py"
    path.write_text(fits + "\n\n" + over)
    found = long_functions(path)
    assert len(found) == 1 and found[0].endswith(" over (61 lines)")
