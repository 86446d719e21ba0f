"""The documentation site builds strictly, offline, and covers the package.

``mkdocs build --strict`` fails on a broken link, a missing anchor, a
cross-reference mkdocstrings cannot resolve or a docstring that names a
parameter the signature lacks. On top of the build, these tests check what
strict mode does not: every page is in the navigation, every name of
``closedchain.__all__`` has its API entry, nothing is fetched from the web,
README.md stays a front door, and measurements stay in generated pages.
"""

from __future__ import annotations

import functools
import importlib.util
import inspect
import os
import re
import subprocess
import sys
import zlib
from pathlib import Path

import pytest

import closedchain

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
CONFIG = ROOT / "mkdocs.yml"
README = ROOT / "README.md"
CHANGELOG = ROOT / "CHANGELOG.md"
#: Pages written by the scripts that measure (scripts/bench_extras.py --report,
#: scripts/nfourbar_cost.py --page), each with its run in the header (scripts/bench_page.py).
GENERATED_PAGES = (
    DOCS / "bench" / "results.md",
    DOCS / "bench" / "nfourbar.md",
    DOCS / "bench" / "corpus.md",  # scripts/check_corpus.py --out
    DOCS / "bench" / "percall.md",  # scripts/bench_extras.py --parts percall
    DOCS / "bench" / "couplings.md",  # scripts/bench_extras.py --parts couplings
)
#: The issue's bound on the README (a front door, not a manual).
README_MAX_LINES = 300
#: The site's build takes about 10 s; more means something hangs (a fetch).
BUILD_TIMEOUT_S = 600
#: Hosts the site must not load anything from (material's default web fonts).
WEB_FONT_HOSTS = ("fonts.googleapis.com", "fonts.gstatic.com")
#: Lab-notebook figures that belong in generated pages or CHANGELOG.md, not in prose.
NOTEBOOK_PATTERNS = {
    "a commit hash": re.compile(r"\bcommit(?:s)? [0-9a-f]{7,40}\b"),
    "a load average": re.compile(r"\bload(?: average)? (?:of |about |~)?\d"),
    "an issue number": re.compile(r"\bissue #?\d+", re.I),
}

needs_mkdocs = pytest.mark.skipif(
    any(importlib.util.find_spec(m) is None for m in ("mkdocs", "material", "mkdocstrings")),
    reason="mkdocs, mkdocs-material or mkdocstrings is not installed (pip install '.[test]')",
)


def mkdocs_config() -> dict:
    """mkdocs.yml as data (it uses no custom YAML tags)."""
    yaml = pytest.importorskip("yaml")
    return yaml.safe_load(CONFIG.read_text())


def nav_pages(nav) -> list[str]:
    """Return the page paths of a mkdocs ``nav`` tree, in order."""
    if isinstance(nav, str):
        return [nav]
    if isinstance(nav, list):
        return [p for item in nav for p in nav_pages(item)]
    if isinstance(nav, dict):
        return [p for value in nav.values() for p in nav_pages(value)]
    return []


def site_pages(config: dict) -> list[str]:
    """Return the Markdown files of docs/ that mkdocs builds (``exclude_docs`` left out)."""
    pathspec = pytest.importorskip("pathspec")
    excluded = pathspec.GitIgnoreSpec.from_lines(config.get("exclude_docs", "").splitlines())
    pages = (p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md"))
    return sorted(p for p in pages if not excluded.match_file(p))


def inventory_names(path: Path) -> set[str]:
    """Return the object names of a Sphinx ``objects.inv`` (version 2) file."""
    raw = path.read_bytes()
    header_lines = 4
    parts = raw.split(b"\n", header_lines)
    assert parts[0].startswith(b"# Sphinx inventory version 2"), parts[0]
    body = zlib.decompress(parts[header_lines]).decode()
    return {line.split(" ", 1)[0] for line in body.splitlines() if line.strip()}


def canonical_path(name: str) -> str:
    """Where ``closedchain.<name>`` is defined (the anchor of its API entry)."""
    obj = getattr(closedchain, name)
    if inspect.isclass(obj) or inspect.isfunction(obj):
        return f"{obj.__module__}.{obj.__qualname__}"
    return griffe_package()[name].canonical_path


@functools.cache
def griffe_package():
    """The package as mkdocstrings sees it (griffe, from the sources)."""
    griffe = pytest.importorskip("griffe")
    return griffe.load("closedchain", search_paths=[str(ROOT / "src")])


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """Build the site once, strictly; return its directory."""
    out = tmp_path_factory.mktemp("site")
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(CONFIG), "-d", str(out)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=BUILD_TIMEOUT_S,
    )
    warnings = [ln for ln in proc.stderr.splitlines() if "WARNING" in ln or "ERROR" in ln]
    assert proc.returncode == 0, "mkdocs build --strict failed:\n" + "\n".join(
        warnings or proc.stderr.splitlines()[-30:]
    )
    return out


@needs_mkdocs
def test_site_builds_strictly(site):
    assert (site / "index.html").is_file()
    assert (site / "api" / "mechanism" / "index.html").is_file()


@needs_mkdocs
def test_every_public_name_has_an_api_entry(site):
    names = inventory_names(site / "objects.inv")
    missing = [n for n in closedchain.__all__ if canonical_path(n) not in names]
    assert not missing, f"closedchain.__all__ names without an API entry: {missing}"


@needs_mkdocs
def test_the_site_loads_nothing_from_the_web(site):
    assert mkdocs_config()["theme"].get("font") is False, "mkdocs.yml: set theme.font: false"
    for page in site.rglob("*.html"):
        text = page.read_text(errors="replace")
        hosts = [h for h in WEB_FONT_HOSTS if h in text]
        assert not hosts, f"{page.relative_to(site)} loads from {hosts}"


def test_every_page_is_in_the_nav():
    config = mkdocs_config()
    nav = nav_pages(config["nav"])
    pages = site_pages(config)
    assert sorted(set(nav)) == pages, (
        f"pages not in mkdocs.yml's nav: {sorted(set(pages) - set(nav))}; "
        f"nav entries without a page: {sorted(set(nav) - set(pages))}"
    )
    assert len(nav) == len(set(nav)), f"pages listed twice in the nav: {nav}"


def test_every_public_module_has_an_api_page():
    modules = sorted(
        p.stem if p.is_file() else p.name
        for p in (ROOT / "src" / "closedchain").iterdir()
        if not p.name.startswith("_")
        and (p.suffix == ".py" or (p / "__init__.py").is_file())
        and p.stem != "cli"  # the command: documented in guide/command-line.md
    )
    for module in modules:
        page = DOCS / "api" / f"{module}.md"
        assert page.is_file(), f"closedchain.{module} has no API page docs/api/{module}.md"
        assert f"::: closedchain.{module}" in page.read_text(), page


def test_readme_is_a_front_door():
    lines = README.read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, (
        f"README.md has {len(lines)} lines, at most {README_MAX_LINES}: move the detail "
        "into docs/ (the manual) and history into CHANGELOG.md"
    )


def test_prose_carries_no_lab_notebook():
    """Commit hashes, load averages and issue numbers live in generated pages (whose
    header names the run) and in CHANGELOG.md, never in the README or the manual."""
    generated = set(GENERATED_PAGES)
    documents = [README, *sorted(DOCS.rglob("*.md"))]
    for doc in documents:
        if doc in generated:
            continue
        text = doc.read_text()
        for what, pattern in NOTEBOOK_PATTERNS.items():
            found = pattern.search(text)
            assert not found, f"{doc.relative_to(ROOT)} carries {what}: {found[0]!r}"


@pytest.mark.parametrize("page", GENERATED_PAGES, ids=lambda p: p.name)
def test_generated_pages_name_their_run(page):
    text = page.read_text()
    name = page.relative_to(ROOT).as_posix()
    assert text.startswith("# "), f"{name} needs a title"
    for field in ("command", "date", "machine"):
        row = re.search(rf"^\| {field} \| (.+) \|$", text, re.M)
        assert row, f"{name}: no {field} row in its header"
        assert row[1].strip() not in ("", "not recorded"), f"{name}: {field} not recorded"


def test_changelog_has_the_package_version():
    text = CHANGELOG.read_text()
    assert re.search(rf"^## \[{re.escape(closedchain.__version__)}\]", text, re.M), (
        f"CHANGELOG.md has no section for version {closedchain.__version__}"
    )


# -- the helpers themselves -------------------------------------------------------------------


def test_nav_pages_of_a_nested_nav():
    nav = [{"Home": "index.md"}, {"Guide": [{"A": "guide/a.md"}, "guide/b.md"]}]
    assert nav_pages(nav) == ["index.md", "guide/a.md", "guide/b.md"]


def test_notebook_patterns_catch_what_they_name():
    assert NOTEBOOK_PATTERNS["a commit hash"].search("since commit e30a4eb (shared)")
    assert NOTEBOOK_PATTERNS["a load average"].search("13.9 min at load average 2.28")
    assert NOTEBOOK_PATTERNS["an issue number"].search("the default before issue 11")
    assert not any(
        p.search("the load-time row sampling, 2 issues") for p in NOTEBOOK_PATTERNS.values()
    )


def test_sphinx_roles_become_markdown():
    spec = importlib.util.spec_from_file_location("sphinx_roles", DOCS / "_ext" / "sphinx_roles.py")
    if importlib.util.find_spec("griffe") is None:
        pytest.skip("griffe is not installed (pip install '.[test]')")
    roles = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(roles)
    text = (
        "Use :func:`~closedchain.load` or :data:`METHODS`, :math:`M a`.\n\n.. math::\n\n    x = 1\n"
    )
    assert roles.markdown(text) == "Use `load` or `METHODS`, `M a`.\n\n\n\n    x = 1\n"
