"""Keep README.md from going stale (in the manner of robot_descriptions' test_readme.py).

The contract: README.md has a "Quick start" section with exactly two shell
commands in fenced code blocks; every ``closedchain <subcommand>`` the README
and the documentation pages (docs/) show exists in
:func:`closedchain.cli.build_parser` and parses; the files its commands name
exist; the Python examples of the README and of the self-contained docs pages
run as written; and the CI script ``.ci/run`` runs the second quick-start command.
"""

from __future__ import annotations

import argparse
import re
import shlex
from pathlib import Path

import pytest

from closedchain import cli

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
#: The documents whose commands are checked: the README and the site's pages.
DOCUMENTS = [README, *sorted((ROOT / "docs").rglob("*.md"))]
CI_SCRIPT = ROOT / ".ci" / "run"

#: Info strings of fenced blocks that hold shell commands.
SHELL_LANGUAGES = {"", "sh", "bash", "shell", "console", "zsh"}

FENCE = re.compile(r"^(```|~~~)\s*([\w+-]*)[^\n]*\n(.*?)^\1\s*$", re.M | re.S)
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$", re.M)
#: Tokens that may precede the program name: ``python -m closedchain``, ``uv run closedchain``.
LAUNCHERS = {"-m", "run", "exec"}
INLINE_CODE = re.compile(r"(?<!`)`([^`\n]+)`(?!`)")


def shell_commands(block: str) -> list[str]:
    """Return the commands of a shell block: prompts stripped, continuations joined."""
    lines = block.splitlines()
    prompted = any(ln.lstrip().startswith("$ ") for ln in lines)
    commands: list[str] = []
    pending = ""
    for line in lines:
        text = line.strip()
        if pending:
            text = pending + " " + text
            pending = ""
        elif prompted:
            if not text.startswith("$ "):
                continue  # output of a console session
            text = text[2:].strip()
        if not text or text.startswith("#"):
            continue
        if text.endswith("\\"):
            pending = text[:-1].strip()
            continue
        commands.append(text)
    if pending:
        commands.append(pending)
    return commands


def shell_blocks(markdown: str) -> list[str]:
    return [m[3] for m in FENCE.finditer(markdown) if m[2].lower() in SHELL_LANGUAGES]


def section(markdown: str, title: str) -> str:
    """Return the body of the first heading whose text contains ``title`` (case-insensitive)."""
    headings = list(HEADING.finditer(markdown))
    for i, h in enumerate(headings):
        if title.lower() in h[2].lower():
            level = len(h[1])
            end = len(markdown)
            for nxt in headings[i + 1 :]:
                if len(nxt[1]) <= level and not _inside_fence(markdown, nxt.start()):
                    end = nxt.start()
                    break
            return markdown[h.end() : end]
    raise AssertionError(f"README.md has no {title!r} section")


def _inside_fence(markdown: str, pos: int) -> bool:
    return any(m.start() < pos < m.end() for m in FENCE.finditer(markdown))


def closedchain_argv(command: str) -> list[str] | None:
    """Return the arguments after ``closedchain`` (or ``python -m closedchain``), else None."""
    try:
        tokens = shlex.split(command, comments=True)
    except ValueError:
        return None
    for i, tok in enumerate(tokens):
        if Path(tok).name == "closedchain" and (i == 0 or tokens[i - 1] in LAUNCHERS):
            return tokens[i + 1 :]
    return None


def subcommands() -> set[str]:
    parser = cli.build_parser()
    actions = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    assert len(actions) == 1
    return set(actions[0].choices)


def read_readme() -> str:
    assert README.is_file(), "README.md is missing"
    return README.read_text()


def quick_start_commands() -> list[str]:
    body = section(read_readme(), "Quick start")
    return [cmd for block in shell_blocks(body) for cmd in shell_commands(block)]


def test_quick_start_has_exactly_two_commands():
    quick_start = quick_start_commands()
    assert len(quick_start) == 2, quick_start


def document_id(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


@pytest.mark.parametrize("document", DOCUMENTS, ids=document_id)
def test_every_closedchain_subcommand_shown_exists(document):
    text = document.read_text()
    name = document_id(document)
    known = subcommands()
    mentioned: list[tuple[str, list[str]]] = []
    for block in shell_blocks(text):
        for cmd in shell_commands(block):
            argv = closedchain_argv(cmd)
            if argv:
                mentioned.append((cmd, argv))
    for span in INLINE_CODE.findall(text):
        argv = closedchain_argv(span)
        if argv and not argv[0].startswith("-") and "<" not in span:
            mentioned.append((span, argv))
    if document == README:
        assert mentioned, "README.md shows no closedchain command"
    for shown, argv in mentioned:
        sub = next((a for a in argv if not a.startswith("-")), None)
        assert sub in known, f"{name} shows {shown!r}: no subcommand {sub!r} in {sorted(known)}"


@pytest.mark.parametrize("document", DOCUMENTS, ids=document_id)
def test_commands_shown_parse_and_name_existing_files(document):
    name = document_id(document)
    parser = cli.build_parser()
    for block in shell_blocks(document.read_text()):
        for cmd in shell_commands(block):
            argv = closedchain_argv(cmd)
            if not argv or argv[0] in ("-h", "--help") or "--help" in argv or "-h" in argv:
                continue
            try:
                parser.parse_args(argv)
            except SystemExit as exc:
                raise AssertionError(f"{name}: command does not parse: {cmd!r}") from exc
            for arg in argv:
                if arg.endswith(".urdf") and not Path(arg).is_absolute():
                    assert (ROOT / arg).is_file(), f"{name}: command {cmd!r}: no file {arg}"


def test_ci_runs_the_second_quick_start_command():
    quick_start = quick_start_commands()
    assert CI_SCRIPT.is_file(), ".ci/run is missing"
    assert len(quick_start) == 2, quick_start
    wanted = " ".join(quick_start[1].split())
    lines = [" ".join(ln.split()) for ln in CI_SCRIPT.read_text().splitlines()]
    assert any(wanted in ln for ln in lines if not ln.startswith("#")), (
        f".ci/run does not run the second quick-start command {quick_start[1]!r}"
    )


# -- the parsing helpers themselves -----------------------------------------------------------

EXAMPLE = """# Project

Text with `closedchain info models/fourbar.urdf` inline.

## Quick start

```bash
pip install -e . \\
    --quiet
# a comment
closedchain validate models/fourbar.urdf --samples 20
```

```python
import closedchain as cc
```

## Next
```console
$ closedchain info models/agile_eye.urdf
mobility 3
```
"""


def test_helpers_on_an_example():
    body = section(EXAMPLE, "Quick start")
    commands = [c for b in shell_blocks(body) for c in shell_commands(b)]
    assert commands == [
        "pip install -e . --quiet",
        "closedchain validate models/fourbar.urdf --samples 20",
    ]
    all_commands = [c for b in shell_blocks(EXAMPLE) for c in shell_commands(b)]
    assert all_commands[-1] == "closedchain info models/agile_eye.urdf"
    assert closedchain_argv("python -m closedchain info x.urdf") == ["info", "x.urdf"]
    assert closedchain_argv("import closedchain as cc") is None
    assert INLINE_CODE.findall(EXAMPLE) == ["closedchain info models/fourbar.urdf"]


def test_readme_python_blocks_run(tmp_path, monkeypatch):
    """Every ```python block of the README runs as written (in a scratch directory
    where ``models/`` is the repository's)."""
    blocks = [m[3] for m in FENCE.finditer(read_readme()) if m[2].lower() == "python"]
    assert blocks, "README.md shows no Python example"
    (tmp_path / "models").symlink_to(ROOT / "models")
    monkeypatch.chdir(tmp_path)
    for block in blocks:
        exec(compile(block, "README.md", "exec"), {"__name__": "readme_example"})
    assert (tmp_path / "fourbar.html").is_file()


#: Pages of the site whose ```python blocks run as written, in order (the others show
#: fragments that continue an example).
RUNNABLE_PAGES = (
    "docs/index.md",
    "docs/guide/mechanisms-and-loops.md",
    "docs/guide/dynamics-methods.md",
    "docs/guide/simulation.md",
)


@pytest.mark.parametrize("page", RUNNABLE_PAGES)
def test_docs_python_examples_run(page, tmp_path, monkeypatch):
    text = (ROOT / page).read_text()
    blocks = [m[3] for m in FENCE.finditer(text) if m[2].lower() == "python"]
    assert blocks, f"{page} shows no Python example"
    (tmp_path / "models").symlink_to(ROOT / "models")
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "docs_example"}
    for block in blocks:
        exec(compile(block, page, "exec"), namespace)
