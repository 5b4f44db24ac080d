"""The layers: no stage package imports another. Stages share only n2d_common (formats, geometry, ROS helpers),
n2d_interfaces and the bpy layer n2d_blender; the bringup package `n2d` alone composes the stages."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
STAGES = ("n2d_capture", "n2d_reconstruct", "n2d_dataset", "n2d_dope", "n2d_sim")
ALLOWED = {**{stage: {"n2d_common", "n2d_interfaces", "n2d_blender"} for stage in STAGES},
           "n2d_blender": {"n2d_common"}, "n2d_common": {"n2d_interfaces"}}
"""Package -> the n2d packages it may import besides itself."""


def _n2d_imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return {n for n in names if n.startswith("n2d")}


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_no_stage_imports_another(package):
    bad = []
    for path in sorted((ROOT / package / package).rglob("*.py")):
        for name in _n2d_imports(path) - ALLOWED[package] - {package}:
            bad.append(f"{path.relative_to(ROOT)} imports {name}")
    assert not bad, "\n".join(bad)
