"""The front page and the manual: their code runs as written, their claims hold.

Every ```python block of README.md and of the docs' pages runs (each page's blocks in order, in
one fresh interpreter, from the repository's root, as a reader pastes them); the README stays a
front page; the set-up command works with and without sudo and is the one CI runs; every public
function and class of certpose and solvers has a docstring and a place in the API reference.
"""

from __future__ import annotations

import importlib
import inspect
import os
import pkgutil
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import require_data

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def python_blocks(path: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(), re.S)


PAGES_WITH_CODE = [p for p in PAGES if python_blocks(p)]


@pytest.mark.slow
@pytest.mark.parametrize("page", PAGES_WITH_CODE, ids=lambda p: str(p.relative_to(ROOT)))
def test_the_pages_python_blocks_run_as_written(page: Path) -> None:
    code = "\n".join(python_blocks(page))
    for data in sorted(set(re.findall(r"\.\./shared/data/(\w+)", code))):
        require_data(data)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"}
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0, f"{page.name}:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}"


def test_readme_is_a_front_page() -> None:
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 250
    assert len(PAGES_WITH_CODE) >= 5 and len(python_blocks(ROOT / "README.md")) == 3
    # No history, load averages of the notebook kind, issue numbers or missing files.
    for bad in ("NOTES.md", "issue #", "issue 1", "load average", "since 20"):
        assert bad not in text, bad
    # Every row of the results table says how it was measured and when.
    table = text.split("## Results")[1].split("\n## ")[0]
    rows = [r for r in table.splitlines() if r.startswith("| ") and not r.startswith("| what")]
    assert len(rows) >= 6
    for row in rows:
        assert re.search(r"20\d\d-\d\d-\d\d", row) and ("`" in row or "same" in row), row
    # The rotation scope is said not to certify certpose's own pose.
    assert "refuses certpose's own pose by design" in text


def test_links_of_the_readme_and_the_docs_exist() -> None:
    for page in PAGES:
        for target in re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", page.read_text()):
            assert (page.parent / target).exists(), f"{page.relative_to(ROOT)} links {target}"


def setup_command() -> str:
    (line,) = [x for x in (ROOT / "README.md").read_text().splitlines()
               if x.startswith("$(command -v sudo) apt-get")]
    return line


def test_setup_command_works_without_sudo_and_is_what_ci_runs(tmp_path: Path) -> None:
    line = setup_command()
    assert "sudo apt-get" not in line.replace("$(command -v sudo) apt-get", "")
    assert 'pip install -e ".[dev]"' in line and line.endswith("certpose pose --demo")
    # On a machine without sudo (a container where one is root) the prefix expands to nothing.
    probe = line.split(" && ")[0].replace("apt-get update", "echo apt-get update")
    env = {"PATH": str(tmp_path), "HOME": str(tmp_path)}
    (tmp_path / "echo").symlink_to("/bin/echo")
    out = subprocess.run(["/bin/bash", "-c", probe], env=env, capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == "apt-get update", out
    # ... and with sudo on the PATH, to sudo.
    (tmp_path / "sudo").write_text("#!/bin/sh\necho sudo \"$@\"\n")
    (tmp_path / "sudo").chmod(0o755)
    out = subprocess.run(["/bin/bash", "-c", probe], env=env, capture_output=True, text=True)
    assert out.stdout.strip() == "sudo echo apt-get update", out
    # CI runs the README's own line, then builds the site strictly.
    ci = (ROOT / ".ci" / "run").read_text()
    assert "$(command -v sudo) apt-get" in ci and "README.md" in ci
    assert "mkdocs build --strict" in ci and '".[docs]"' in ci


def public_modules() -> list[str]:
    import certpose
    import solvers

    names = []
    for pkg in (certpose, solvers):
        names.append(pkg.__name__)
        for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
            if not any(part.startswith("_") for part in m.name.split(".")):
                names.append(m.name)
    return names


def test_every_public_name_has_a_docstring() -> None:
    missing = []
    for name in public_modules():
        module = importlib.import_module(name)
        if not (module.__doc__ or "").strip():
            missing.append(name)
        for attr in getattr(module, "__all__", ()):
            obj = getattr(module, attr)
            if not (inspect.isclass(obj) or inspect.isfunction(obj)):
                continue
            doc = (obj.__doc__ or "").strip()
            # A dataclass without a docstring gets its signature as __doc__.
            if not doc or (inspect.isclass(obj) and doc.startswith(f"{obj.__name__}(")):
                missing.append(f"{name}.{attr}")
    assert not missing, missing


def test_every_public_module_is_in_the_api_reference() -> None:
    text = "\n".join(p.read_text() for p in (ROOT / "docs" / "reference").glob("*.md"))
    listed = set(re.findall(r"^::: (\S+)", text, re.M))
    wanted = {m for m in public_modules() if not m.startswith("certpose.cli")}
    assert wanted <= listed, sorted(wanted - listed)
    nav = (ROOT / "mkdocs.yml").read_text()
    for page in (ROOT / "docs" / "reference").glob("*.md"):
        assert f"reference/{page.name}" in nav, page.name


def test_the_code_cites_no_missing_file_issue_or_date() -> None:
    # Reasons stay in docstrings as facts; the history (dates, issue numbers, notes outside the
    # repository) does not.
    pattern = re.compile(r"NOTES\.md|issue [0-9]|20[0-9][0-9]-[0-9][0-9]-")
    hits = [f"{p.relative_to(ROOT)}:{k}: {line.strip()}"
            for pkg in ("certpose", "solvers") for p in sorted((ROOT / pkg).rglob("*.py"))
            for k, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
            if pattern.search(line)]
    assert not hits, "\n".join(hits)
