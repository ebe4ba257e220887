"""A lighter install: the registration solver and its certificates import neither open3d nor
gtsam, and the declared dependencies are exactly the imported ones."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# Distribution name -> the module it provides, where they differ.
MODULE_OF = {"pillow": "PIL", "opencv-python-headless": "cv2"}
# Declared but never imported by name: cvxpy's SDP backend, selected by name (cp.CLARABEL).
NAMED_NOT_IMPORTED = {"clarabel"}
# Dev-only tools (run, not imported by the package); the docs extra builds the site.
DOCS = {"mkdocs", "mkdocs_material", "mkdocstrings"}
TOOLS = {"pytest", "hypothesis", "ruff", "networkx", "pandas"}


def _requirements(items: list[str]) -> set[str]:
    names = {re.split(r"[<>=!~\[ ;]", item, maxsplit=1)[0].lower() for item in items}
    return {MODULE_OF.get(n, n.replace("-", "_")) for n in names}


def _third_party_imports() -> set[str]:
    stdlib = set(sys.stdlib_module_names)
    found = set()
    for path in [*REPO.glob("certpose/**/*.py"), *REPO.glob("solvers/**/*.py")]:
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            found |= {n.split(".")[0] for n in names}
    # String imports of optional extras (certpose.bench.rows.bench_extra).
    for path in REPO.glob("certpose/**/*.py"):
        found |= set(re.findall(r'bench_extra\("([a-z_]+)', path.read_text(encoding="utf-8")))
    return {n for n in found if n not in stdlib and n not in ("certpose", "solvers")}


def test_declared_dependencies_are_the_imported_ones():
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    meta = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    core = _requirements(meta["dependencies"])
    extras = {k: _requirements(v) for k, v in meta["optional-dependencies"].items()}
    optional = set().union(*(v for k, v in extras.items() if k != "dev"))
    # llvmlite: numba's own dependency; teaserpp_python: built from source (no wheel).
    imported = _third_party_imports() - {"llvmlite", "teaserpp_python"}
    assert imported <= core | optional, f"imported, not declared: {imported - core - optional}"
    assert core - NAMED_NOT_IMPORTED <= imported, f"declared, never imported: {core - imported}"
    # distributed: imported through bench_extra's string; emcee and PyMC: the samplers extra
    # installs what certpose.sampling.initialisers prepares inputs for (the examples run them).
    unused = optional - imported - {"distributed", "emcee", "pymc"} - DOCS
    assert not unused, f"extras never imported: {unused}"
    assert "igraph" not in core | optional
    # [dev] installs everything the tests need: every extra's packages.
    tests_skip_without = {"torch"} | DOCS  # torch: a large download, its tests skip; DOCS: CI installs [docs]
    missing = optional - extras["dev"] - tests_skip_without
    assert not missing, f"missing from [dev]: {missing}"
    assert not {"open3d", "gtsam", "imageio", "cv2"} & core


def test_registration_and_certificates_import_neither_open3d_nor_gtsam():
    code = """
import sys
import numpy as np
import certpose
from certpose.cli import main
rng = np.random.default_rng(0)
src = rng.normal(size=(40, 3))
r1 = certpose.register(src, src + 1.0, noise_bound=0.01, certify=True)
r2 = certpose.register(src, src + 1.0, noise_bound=0.01, solver="sdp")
assert r1.certificate.certified and r2.success, (r1.message, r2.message)
assert main(["register", "--demo", "--certify", "-q"]) == 0
heavy = {"open3d", "gtsam", "cv2", "imageio", "PIL", "matplotlib", "dask", "distributed"}
print(sorted(heavy & {m.split(".")[0] for m in sys.modules}))
"""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip().splitlines()[-1] == "[]"


def test_a_missing_extra_is_named(capsys):
    from certpose.cli import _message

    assert "pip install 'certpose[pose]'" in _message(
        ModuleNotFoundError("No module named 'open3d'", name="open3d"))
    assert "pip install 'certpose[bench]'" in _message(
        ModuleNotFoundError("No module named 'gtsam'", name="gtsam"))
