"""The layers import one way: flows -> tasks -> btfcore (docs/architecture.md, "Layers")."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ORCHESTRATION = {"dask", "distributed", "prefect", "prefect_dask", "zarr", "fsspec"}
#: What each layer may not import, directly or at any depth of its own modules.
FORBIDDEN = {
    "btfcore": ORCHESTRATION | {"tasks", "flows", "pathlib", "rawpy", "OpenEXR", "tifffile"},
    "tasks": {"flows", "prefect", "prefect_dask"},
    "flows": set(),
}


def _imports(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name.split(".")[0]) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module.split(".")[0]))
    return found


@pytest.mark.parametrize("layer", sorted(FORBIDDEN))
def test_layer_imports_go_one_way(layer: str) -> None:
    files = sorted((ROOT / layer).rglob("*.py"))
    assert files, f"layer {layer} has no modules"
    bad = [f"{path.relative_to(ROOT)}:{line} imports {name}"
           for path in files for line, name in _imports(path) if name in FORBIDDEN[layer]]
    assert not bad, "imports against the layer direction:\n" + "\n".join(bad)


def test_btfcore_pulls_in_no_orchestration_package() -> None:
    """Importing every btfcore module loads none of dask, distributed, prefect, zarr, fsspec."""
    modules = sorted(
        ".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        for p in (ROOT / "btfcore").rglob("*.py")
    )
    code = (
        "import importlib, sys\n"
        f"for m in {modules!r}: importlib.import_module(m)\n"
        f"print(sorted({{m.split('.')[0] for m in sys.modules}} & set({sorted(ORCHESTRATION)!r})))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]", f"btfcore transitively imports {out.stdout.strip()}"


def test_btfcore_does_no_file_io() -> None:
    """btfcore is numerics on arrays: no open(), no paths."""
    bad = []
    for path in sorted((ROOT / "btfcore").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "open":
                bad.append(f"{path.relative_to(ROOT)}:{node.lineno} calls open()")
            if isinstance(node, ast.Attribute) and node.attr in {"imread", "imwrite", "load", "save"} \
                    and isinstance(node.value, ast.Name) and node.value.id in {"cv2", "np", "numpy", "torch"}:
                bad.append(f"{path.relative_to(ROOT)}:{node.lineno} calls {node.value.id}.{node.attr}")
    assert not bad, "\n".join(bad)
