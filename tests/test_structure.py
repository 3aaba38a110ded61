"""The package's structure: layers that import only downwards, and a README that names every module."""
import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "hemirad"
# The pipeline, bottom up (docs/DESIGN.md §6); the top-level modules come last.
LAYERS = ("core", "geometry", "scene", "transport", "adaptive", "lighting", "output", "evaluation")
TOP = len(LAYERS)


def layer_of(module: str) -> int:
    """The layer of a dotted module name inside hemirad (``hemirad.transport.solver``)."""
    parts = module.split(".")
    return LAYERS.index(parts[1]) if len(parts) > 1 and parts[1] in LAYERS else TOP


def modules() -> dict[str, Path]:
    return {".".join(p.relative_to(ROOT).with_suffix("").parts): p for p in PACKAGE.rglob("*.py")}


def hemirad_imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import of a hemirad module in the file, those inside
    functions and ``if TYPE_CHECKING`` blocks included."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("hemirad"):
            names = [f"{node.module}.{a.name}" if node.module == "hemirad" else node.module for a in node.names]
            found += [(node.lineno, name) for name in names]
        elif isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names if a.name.startswith("hemirad")]
        elif isinstance(node, ast.ImportFrom) and node.level:
            found.append((node.lineno, "." * node.level + (node.module or "")))
    return found


def test_every_import_points_down_the_pipeline():
    upward, relative = [], []
    for name, path in modules().items():
        for line, imported in hemirad_imports(path):
            if imported.startswith("."):
                relative.append(f"{name}:{line}")
            elif layer_of(imported) > layer_of(name):
                upward.append(f"{name}:{line} imports {imported}")
    assert not relative, f"relative imports (the package imports absolutely): {relative}"
    assert not upward, "imports that reach up a layer:\n" + "\n".join(upward)


def test_the_check_sees_an_upward_import():
    # the solver reaching into the adaptive stage, as it once did
    assert layer_of("hemirad.adaptive.refine") > layer_of("hemirad.transport.solver")
    assert layer_of("hemirad.core.colour") < layer_of("hemirad.output.display") < layer_of("hemirad.pipeline")


def test_the_readme_module_table_matches_the_tree():
    readme = (ROOT / "README.md").read_text()
    section = readme[readme.index("## How it works"):]
    section = section[:section.index("\n## ", 1)]
    first_cells = [line.split("|")[1] for line in section.splitlines() if line.startswith("| `")]
    named = {name for cell in first_cells for name in re.findall(r"`((?:[a-z_]+/)?[a-z_]+\.py)`", cell)}
    present = {str(p.relative_to(PACKAGE)) for p in PACKAGE.rglob("*.py")
               if p.name not in ("__init__.py", "__main__.py")}
    assert named == present, (f"in the tree, not in the README's table: {sorted(present - named)}; "
                              f"in the table, not in the tree: {sorted(named - present)}")
