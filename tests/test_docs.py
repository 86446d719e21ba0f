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
import importlib
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
    DOCS / "bench" / "scaling.md",  # scripts/bench_extras.py --parts scaling
    DOCS / "bench" / "couplings.md",  # scripts/bench_extras.py --parts couplings
    DOCS / "bench" / "batch.md",  # scripts/bench_batch.py --page
    DOCS / "bench" / "mjcf_models.md",  # scripts/check_mjcf_models.py (local copies)
    DOCS / "bench" / "front.md",  # scripts/bench_front.py --page
)
#: The issue's bound on the README (a front door, not a manual).
README_MAX_LINES = 300
#: The site's build takes about 10 s; more means something hangs (a fetch).
BUILD_TIMEOUT_S = 600
#: Hosts the site must not load anything from (material's default web fonts).
WEB_FONT_HOSTS = ("fonts.googleapis.com", "fonts.gstatic.com")
#: A LaTeX command or bracket left as text: maths that did not become MathML.
RAW_LATEX = re.compile(r"\\(?:[A-Za-z]{2,}|[\[\](){}])")
#: Elements whose text may hold LaTeX on purpose (code, and MathML's own copy of its source).
VERBATIM_ELEMENTS = ("pre", "code", "script", "style", "annotation", "textarea")
#: A Markdown list written in a docstring or page that rendered as one paragraph.
COLLAPSED_LIST = re.compile(r"(?:^|\n)[ \t]*(?:[*+-]|\d+\.) \S")
#: Lab-notebook figures that belong in generated pages or CHANGELOG.md, not in prose.
NOTEBOOK_PATTERNS = {
    "a commit hash": re.compile(r"\bcommit(?:s)? [0-9a-f]{7,40}\b"),
    "a load average": re.compile(r"\bload(?: average)? (?:of |about |~)?\d"),
    "an issue number": re.compile(r"\bissue #?\d+", re.I),
}
#: The in-house name of the lesson the project grew from (cited as "the lesson" in
#: references.md) and of its settings; "the seed of the sampling" (a random seed) is fine.
IN_HOUSE_NAMES = re.compile(r"\bseed(?:'s|_settings)\b|\bthe seed\b(?! of\b)", re.I)

needs_mkdocs = pytest.mark.skipif(
    any(
        importlib.util.find_spec(m) is None
        for m in ("mkdocs", "material", "mkdocstrings", "latex2mathml")
    ),
    reason="mkdocs, mkdocs-material, mkdocstrings or latex2mathml is not installed "
    "(pip install '.[test]')",
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


def page_text(path: Path, *, verbatim: bool = False) -> str:
    """Return the text a reader sees on a built page, without code and MathML annotations
    unless ``verbatim``."""
    lxml_html = pytest.importorskip("lxml.html")
    tree = lxml_html.fromstring(path.read_bytes())
    for element in [] if verbatim else list(tree.iter(*VERBATIM_ELEMENTS)):
        if element.getparent() is not None:
            element.drop_tree()
    return tree.text_content()


@needs_mkdocs
def test_maths_is_rendered_as_mathml(site):
    """No page shows LaTeX source; the pages with equations carry MathML (written at build
    time by docs/_ext/mathml.py, so the site needs no script or network to show them)."""
    raw = {}
    for page in sorted(site.rglob("*.html")):
        found = RAW_LATEX.findall(page_text(page))
        if found:
            raw[page.relative_to(site).as_posix()] = sorted(set(found))[:5]
    assert not raw, f"raw LaTeX on pages: {raw}"
    for page in ("api/simulate/index.html", "guide/dynamics-methods/index.html"):
        text = (site / page).read_text()
        assert "<math" in text, f"{page} shows no maths"
        assert "arithmatex" not in text, f"{page} holds maths that was not converted"


@needs_mkdocs
def test_returns_sections_are_one_row_per_value(site):
    """A Returns section is one value described in prose: its wrapped lines stay one row
    (griffe's ``returns_multiple_items: false`` in mkdocs.yml)."""
    lxml_html = pytest.importorskip("lxml.html")
    split = []
    for page in sorted((site / "api").rglob("*.html")):
        tree = lxml_html.fromstring(page.read_bytes())
        for title in tree.xpath('//span[@class="doc-section-title"][starts-with(., "Returns")]'):
            table = title.getparent().getnext()
            rows = table.xpath(".//tbody/tr") if table is not None else []
            if len(rows) != 1:
                heading = title.xpath("preceding::h2[1] | preceding::h3[1]")
                where = heading[-1].get("id") if heading else "?"
                split.append((page.parent.name, where, len(rows)))
    assert not split, f"Returns tables without exactly one row (page, object, rows): {split}"


@needs_mkdocs
def test_lists_render_as_lists(site):
    """Bullet and definition lists of docstrings and pages stay lists."""
    lxml_html = pytest.importorskip("lxml.html")
    collapsed = []
    for page in sorted(site.rglob("*.html")):
        tree = lxml_html.fromstring(page.read_bytes())
        for paragraph in tree.iter("p"):
            if COLLAPSED_LIST.search(paragraph.text_content()):
                collapsed.append((page.relative_to(site).as_posix(), paragraph.text_content()[:80]))
    assert not collapsed, f"lists rendered as paragraphs: {collapsed}"
    simulate = lxml_html.fromstring((site / "api" / "simulate" / "index.html").read_bytes())
    terms = [dt.text_content() for dt in simulate.iter("dt")]
    assert {'"none"', '"baumgarte"', '"projection"', '"partitioning"'} <= set(terms), terms


@needs_mkdocs
def test_the_site_loads_nothing_from_the_web(site):
    assert mkdocs_config()["theme"].get("font") is False, "mkdocs.yml: set theme.font: false"
    for page in site.rglob("*.html"):
        text = page.read_text(errors="replace")
        hosts = [h for h in WEB_FONT_HOSTS if h in text]
        assert not hosts, f"{page.relative_to(site)} loads from {hosts}"


def page_members(module: str) -> list[str] | None:
    """The ``members:`` list of docs/api/<module>.md, or None where the page has none."""
    yaml = pytest.importorskip("yaml")
    text = (DOCS / "api" / f"{module}.md").read_text()
    options = yaml.safe_load(text.split("\n", 1)[1]) if "\n" in text.strip() else None
    return (options or {}).get("options", {}).get("members")


def public_modules() -> list[str]:
    """The public modules of the package (those with an API page)."""
    return sorted(p.stem for p in (DOCS / "api").glob("*.md") if p.stem != "index")


@needs_mkdocs
def test_api_pages_show_the_public_api_only(site):
    """Each API page shows what its module exports (its ``__all__``, or the page's own
    ``members:`` list for a module without one), nothing else: internals are described
    in the design pages."""
    raw = (site / "objects.inv").read_bytes()
    body = zlib.decompress(raw.split(b"\n", 4)[4]).decode()
    shown: dict[str, set[str]] = {}
    for line in body.splitlines():
        name, _, rest = line.partition(" ")
        uri = rest.split()[2]
        module = uri.split("/")[1] if uri.startswith("api/") else None
        prefix = f"closedchain.{module}."
        if module and name.startswith(prefix) and "." not in name[len(prefix) :]:
            shown.setdefault(module, set()).add(name[len(prefix) :])
    for module in public_modules():
        members = page_members(module)
        exported = getattr(importlib.import_module(f"closedchain.{module}"), "__all__", None)
        public = members if members is not None else exported
        assert public is not None, f"closedchain.{module} has no __all__ and its page no members"
        extra = shown.get(module, set()) - set(public)
        assert not extra, f"docs/api/{module}.md shows names its module does not export: {extra}"


def docs_hook(name: str):
    """A hook module of docs/_ext, imported as mkdocs does."""
    spec = importlib.util.spec_from_file_location(name, DOCS / "_ext" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_readme_states_the_default_that_runs():
    """The site states the default from the constants (docs/_ext/defaults.py); the README,
    which is not built, must say the same."""
    defaults = docs_hook("defaults")
    assert defaults.short() in README.read_text(), (
        f"README.md does not state the default configuration as {defaults.short()!r}"
    )


@needs_mkdocs
def test_pages_state_the_default_that_runs(site):
    from closedchain.simulate import DEFAULT_INTEGRATOR, INTEGRATORS

    defaults = docs_hook("defaults")
    tolerances = INTEGRATORS[DEFAULT_INTEGRATOR].tolerances
    for page in ("index.html", "guide/simulation/index.html"):
        text = page_text(site / page, verbatim=True)
        assert defaults.short() in text, f"{page} does not state the default {defaults.short()!r}"
        assert "{{" not in text, f"{page} has a placeholder left"
    guide = page_text(site / "guide" / "simulation" / "index.html", verbatim=True)
    assert f'integrator="{DEFAULT_INTEGRATOR}", rtol={defaults._num(tolerances[0])}' in guide


#: Pages whose code blocks run, in order, in an empty directory (``title="file"`` blocks of
#: another language are written there first): they teach by running code.
EXECUTED_PAGES = (DOCS / "guide" / "tutorial.md",)
#: A fenced block: language, info string, body.
FENCE = re.compile(r"^```(\w+)([^\n]*)\n(.*?)^```", re.S | re.M)


#: Sections of other pages whose code blocks run as the tutorial's: (page, heading line).
EXECUTED_SECTIONS = (
    (DOCS / "guide" / "robots-and-moving-bases.md", "### A planar five-bar from nothing"),
)


def run_blocks(text: str, page: Path, directory: Path) -> list[tuple[str, str, str]]:
    """Run the fenced blocks of ``text`` in order in ``directory`` (the current one): a
    block of another language with ``title="file"`` is written there, a Python block
    runs; return the blocks."""
    namespace: dict = {"__name__": page.stem}
    blocks = FENCE.findall(text)
    for lang, info, body in blocks:
        title = re.search(r'title="([^"]+)"', info)
        if lang != "python" and title:
            (directory / title[1]).write_text(body)
        elif lang == "python":
            exec(compile(body, str(page), "exec"), namespace)  # noqa: S102 (our own page)
    return blocks


def section(text: str, heading: str) -> str:
    """Return a page's section: from ``heading`` to the next heading of its level or above
    (a ``#`` line inside a fenced block is code, not a heading)."""
    lines = text.splitlines(keepends=True)
    start = lines.index(f"{heading}\n")
    level = len(heading.split(" ", 1)[0])
    fenced = False
    for end in range(start + 1, len(lines)):
        if lines[end].startswith("```"):
            fenced = not fenced
        elif not fenced and re.match(rf"#{{1,{level}}} ", lines[end]):
            return "".join(lines[start:end])
    return "".join(lines[start:])


@pytest.mark.parametrize("page", EXECUTED_PAGES, ids=lambda p: p.stem)
def test_tutorial_code_runs(page, tmp_path, monkeypatch):
    pytest.importorskip("matplotlib")
    monkeypatch.chdir(tmp_path)
    blocks = run_blocks(page.read_text(), page, tmp_path)
    assert sum(lang == "python" for lang, _, _ in blocks) >= 5, f"{page.name}: too few blocks"
    for name in ("slider_crank.html", "slider_crank.png"):
        assert (tmp_path / name).stat().st_size > 0, name


@pytest.mark.parametrize(
    ("page", "heading"), EXECUTED_SECTIONS, ids=[page.stem for page, _ in EXECUTED_SECTIONS]
)
def test_section_code_runs(page, heading, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    blocks = run_blocks(section(page.read_text(), heading), page, tmp_path)
    assert any(lang == "python" for lang, _, _ in blocks), f"{page.name}: no Python block"


def test_section_ends_at_the_next_heading_of_its_level():
    text = "# A\n## B\nb\n```python\n# code\n```\n### C\nc\n## D\nd\n"
    assert section(text, "## B") == "## B\nb\n```python\n# code\n```\n### C\nc\n"
    assert section(text, "## D") == "## D\nd\n"


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


def test_pages_use_no_in_house_names():
    """README.md and every page, generated ones included, say "the lesson", not "the seed"."""
    for doc in [README, *sorted(DOCS.rglob("*.md"))]:
        found = IN_HOUSE_NAMES.search(doc.read_text())
        assert not found, f"{doc.relative_to(ROOT)} uses an in-house name: {found[0]!r}"


@pytest.mark.parametrize("page", GENERATED_PAGES, ids=lambda p: p.name)
def test_generated_pages_name_their_run(page):
    text = page.read_text()
    name = page.relative_to(ROOT).as_posix()
    assert text.startswith("# "), f"{name} needs a title"
    for field in ("command", "date", "machine"):
        row = re.search(rf"^\| {field} \| (.+) \|$", text, re.M)
        assert row, f"{name}: no {field} row in its header"
        assert row[1].strip() not in ("", "not recorded"), f"{name}: {field} not recorded"


@pytest.mark.parametrize("page", GENERATED_PAGES, ids=lambda p: p.name)
def test_generated_pages_state_the_version_and_default_they_measured(page):
    """A page measured under another default than the one that runs must be regenerated
    (``bash scripts/make_bench_figures.sh``): its version row names the default."""
    from closedchain.simulate.request import describe_default

    row = re.search(r"^\| version \| (.+) \|$", page.read_text(), re.M)
    assert row, f"{page.name}: no version row in its header"
    assert row[1].startswith(closedchain.__version__), row[1]
    assert describe_default() in row[1], (
        f"{page.name} measured {row[1]!r}; the default is now {describe_default()!r}: regenerate it"
    )


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


def test_in_house_names_pattern_catches_what_it_names():
    for text in ("the seed's scheme", "seed_settings()", "as the seed does"):
        assert IN_HOUSE_NAMES.search(text), text
    for text in ("--seed 0", "seed=0", "the seed of the sampling", "seeds the row sampling"):
        assert not IN_HOUSE_NAMES.search(text), text


def test_sphinx_roles_become_markdown():
    spec = importlib.util.spec_from_file_location("sphinx_roles", DOCS / "_ext" / "sphinx_roles.py")
    if importlib.util.find_spec("griffe") is None:
        pytest.skip("griffe is not installed (pip install '.[test]')")
    roles = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(roles)
    text = (
        "Use :func:`~closedchain.load` or :data:`METHODS`, :math:`M\n a`.\n\n"
        '.. math::\n\n    x = 1\n\n    y = 2\n\nAfter.\n\n``"a"``\n    the first.\n'
    )
    assert roles.markdown(text).split("\n") == [
        "Use `load` or `METHODS`, $M a$.",
        "",
        "",
        "$$",
        "x = 1",
        "$$",
        "",
        "$$",
        "y = 2",
        "$$",
        "",
        "",
        "After.",
        "",
        '``"a"``',
        ":   the first.",
        "",
    ]


def test_raw_latex_pattern_catches_what_it_names():
    assert RAW_LATEX.search(r"\dot q = v, \qquad M a + h + J^\top\lambda")
    assert RAW_LATEX.search(r"\begin{bmatrix}")
    assert not RAW_LATEX.search("C:/models and a\\ b plain text, 1\\2")
    assert COLLAPSED_LIST.search("the list:\n* one\n* two")
    assert not COLLAPSED_LIST.search("a - b and 3 * 4")
