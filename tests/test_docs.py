"""The documentation: every public name in the API reference, a short README, the benchmarks page's source."""

from __future__ import annotations

import argparse
import contextlib
import importlib
import inspect
import io
import pkgutil
import re
import shlex
import sys
from pathlib import Path

import pytest

import data_synth
import psmini

REPO = Path(__file__).resolve().parents[1]
API = REPO / "docs" / "api"


def _documented_modules() -> set[str]:
    return {m for page in API.glob("*.md") for m in re.findall(r"^::: ([\w.]+)\s*$", page.read_text(), re.M)}


def _public_modules():
    for package in (psmini, data_synth):
        yield package.__name__
        for info in pkgutil.walk_packages(package.__path__, f"{package.__name__}."):
            if not any(part.startswith("_") for part in info.name.split(".")) and ".commands" not in info.name:
                yield info.name


def test_every_public_name_is_in_the_api_reference():
    """Each function and class in a module's ``__all__`` is rendered by a ``::: module`` directive of docs/api/,
    on the module that defines it or the one that lists it."""
    documented = _documented_modules()
    missing = []
    for name in _public_modules():
        module = importlib.import_module(name)
        for public in getattr(module, "__all__", []):
            obj = getattr(module, public)
            if not (inspect.isclass(obj) or inspect.isfunction(obj)):
                continue  # constants are documented with the module that defines them
            owner = obj.__module__
            if owner not in documented and name not in documented and owner.split(".")[0] in ("psmini", "data_synth"):
                missing.append(f"{name}.{public} (defined in {owner})")
    assert not missing, ("add a '::: MODULE' line to a page of docs/api/ (and to mkdocs.yml's nav) for: "
                         + ", ".join(missing))


def test_documented_modules_exist():
    for name in _documented_modules():
        importlib.import_module(name)


def test_readme_is_a_front_page_with_the_ci_commands():
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    assert len(readme.splitlines()) <= 200
    ci = (REPO / ".ci" / "run").read_text(encoding="utf-8")
    for command in ("pip install torch==2.13.0 && pip install -e . && psmini demo",
                    'pip install torch==2.13.0 && pip install -e ".[dev]" && python -m pytest -q -n auto'):
        assert command in readme
        assert command.replace("pip install ", "pip install --quiet ") in ci
    assert "mkdocs build --strict" in ci
    # links into docs/ point at pages that exist (the site build checks the rest)
    for target in re.findall(r"\]\((docs/[^)#]+)", readme):
        assert (REPO / target).is_file(), target


def test_benchmarks_page_takes_the_latest_section_of_each_benchmark():
    sys.path.insert(0, str(REPO / "scripts"))
    try:
        hooks = importlib.import_module("mkdocs_hooks")
    finally:
        sys.path.remove(str(REPO / "scripts"))
    ledger = "# Results\n\n## A (a.py)\n\nold A\n\n## B (b.py)\n\nonly B\n\n## A (a.py)\n\nnew A\n| x |\n"
    assert hooks.latest_sections(ledger) == [("A (a.py)", "new A\n| x |"), ("B (b.py)", "only B")]
    real = hooks.latest_sections((REPO / "benchmarks" / "results.md").read_text(encoding="utf-8"))
    titles = [title for title, _ in real]
    assert len(titles) == len(set(titles)) > 0


def test_readme_is_the_home_page():
    sys.path.insert(0, str(REPO / "scripts"))
    try:
        hooks = importlib.import_module("mkdocs_hooks")
    finally:
        sys.path.remove(str(REPO / "scripts"))
    page = hooks.on_page_markdown((REPO / "docs" / "index.md").read_text(), None, None, None)
    assert page.startswith("# psmini") and "](docs/" not in page and "](getting-started.md)" in page


@pytest.mark.parametrize("page", sorted((REPO / "docs").rglob("*.md")), ids=lambda p: p.relative_to(REPO).as_posix())
def test_pages_hold_no_dated_figures(page):
    """Figures tied to a run (UTC times, commits) live in benchmarks/results.md, not in the guides."""
    text = page.read_text(encoding="utf-8")
    assert not re.search(r"\d\d:\d\d UTC|commit `[0-9a-f]{7}", text), page


_SHELL_BLOCK = re.compile(r"^(?P<indent> *)```(?:bash|sh|shell|console)[^\n]*\n(?P<body>.*?)^(?P=indent)```",
                          re.S | re.M)
_SEPARATORS = {"&&", "||", ";", "&", "|"}


def _shell_commands(line: str) -> list[list[str]]:
    """The simple commands of one shell line, as argument lists, with a synopsis read as one example: optional
    groups (``[--device cuda]``) taken, the first of each set of alternatives (``distant|near``, ``[A | B]``),
    ``<PLACEHOLDER>`` replaced by a dummy word; ``NAME=value`` before a command and redirections dropped."""
    commands: list[list[str]] = [[]]
    depth = skip_to = 0
    words = shlex.split(line, comments=True)
    tokens = iter([part for word in words for part in ([word[:-1], ";"] if word[1:].endswith(";") else [word])])
    for token in tokens:
        opened = depth
        depth += token.count("[") - token.count("]")
        if skip_to:  # the alternatives after the first: skipped to the group's end
            skip_to = 0 if depth < skip_to else skip_to
            continue
        token = re.sub(r"<[A-Za-z][^<>\s]*>", "placeholder", token)
        if token == "|" and opened > 0:
            skip_to = opened
        elif token in _SEPARATORS:
            commands.append([])
        elif re.match(r"\d*(>>?|<)", token):
            if re.fullmatch(r"\d*(>>?|<)", token):
                next(tokens, None)  # the redirection's target
        elif not commands[-1] and re.match(r"\w+=", token):
            continue  # an assignment before the command
        else:
            if opened > 0 or token.startswith("["):
                token = token.lstrip("[").split("|")[0]
                while token.count("]") > token.count("["):
                    token = token[:-1]
            if token:
                commands[-1].append(token)
    return [command for command in commands if command]


def _documented_psmini_commands() -> list[tuple[str, list[str]]]:
    """Every ``psmini ...`` command in the fenced shell blocks of README.md and docs/ (console blocks: the lines
    after a ``$`` prompt), as (``page:line``, arguments after ``psmini``); a line ending in ``\\`` goes on."""
    found = []
    for page in [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]:
        text = page.read_text(encoding="utf-8")
        for block in _SHELL_BLOCK.finditer(text):
            number = text.count("\n", 0, block.start("body"))
            console = block.group(0).lstrip().startswith("```console")
            pending, start = "", 0
            for line in block["body"].splitlines():
                number += 1
                if console and not pending:
                    if not line.startswith("$ "):
                        continue
                    line = line[2:]
                start = start if pending else number
                if line.rstrip().endswith("\\"):
                    pending += line.rstrip()[:-1] + " "
                    continue
                for command in _shell_commands(pending + line):
                    if command[0] == "psmini":
                        found.append((f"{page.relative_to(REPO).as_posix()}:{start}", command[1:]))
                pending = ""
    return found


def test_shell_reader_reads_a_synopsis_as_its_first_example():
    line = ("PYTHONPATH=x psmini batch <ROOT> --out o [--light-model distant|near] [--json] "
            "[--scheduler tcp://H:8786 | --scheduler local[:N]] 2>&1 && dask worker | head > log  # comment")
    assert _shell_commands(line) == [
        ["psmini", "batch", "placeholder", "--out", "o", "--light-model", "distant", "--json", "--scheduler",
         "tcp://H:8786"],
        ["dask", "worker"], ["head"]]


def test_documented_command_lines_parse():
    """Each ``psmini`` line of the README's and the site's shell blocks is accepted by the command's parser as
    written (parsed only, nothing runs): no renamed or removed command, flag or choice, no missing argument."""
    from psmini.cli import build_parser

    commands = _documented_psmini_commands()
    assert len(commands) >= 20, commands  # the reader still finds the pages' commands
    parser = build_parser()
    pending = [parser]
    while pending:  # a flag as written, not a prefix of one (a renamed --pixel-pitch-mm would take --pixel-pitch)
        each = pending.pop()
        each.allow_abbrev = False
        pending += [sub for action in each._actions if isinstance(action, argparse._SubParsersAction)
                    for sub in action.choices.values()]
    failures = []
    for where, argv in commands:
        errors = io.StringIO()
        try:
            with contextlib.redirect_stderr(errors), contextlib.redirect_stdout(io.StringIO()):
                parser.parse_args(argv)
        except SystemExit as exit_:
            if exit_.code:  # --help exits 0
                message = errors.getvalue().strip().splitlines()[-1:] or [f"exit status {exit_.code}"]
                failures.append(f"{where}: psmini {shlex.join(argv)}\n    {message[0]}")
    assert not failures, "documented command lines the parser rejects:\n" + "\n".join(failures)


def _readme_python_blocks() -> list[str]:
    """The README's Python examples, in order (the DiLiGenT one, then the capture one)."""
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    section = readme.split("## From Python", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```python\n(.*?)```", section, re.S)


@pytest.mark.slow
def test_readme_python_example_runs_and_prints_what_it_says(monkeypatch, capsys):
    """The README's DiLiGenT example, run as written from the repository root (so ``../shared/data`` is the
    reference data): it prints the figures its comments state."""
    if not (REPO.parent / "shared" / "data" / "DiLiGenT" / "cat" / "filenames.txt").is_file():
        pytest.skip("DiLiGenT/cat is not in ../shared/data beside the repository")
    pytest.importorskip("plotly", reason="result.show() needs plotly (the viz extra)")
    code = _readme_python_blocks()[0]
    assert len(code.strip().splitlines()) <= 15
    monkeypatch.chdir(REPO)
    namespace: dict = {}
    exec(compile(code, "README.md", "exec"), namespace)  # noqa: S102 (the README's own example)
    printed = capsys.readouterr().out
    assert "lstsq: 8.41° mean angular error" in printed and "robust: 6.43° mean angular error" in printed
    depth = namespace["depth"][namespace["mask"]]
    assert bool((depth > 0).all()) and 0.9 < float(depth.log().mean().exp()) < 1.1


@pytest.mark.slow
def test_readme_capture_example_prints_what_psmini_evaluate_prints(tmp_path, monkeypatch, capsys):
    """The README's capture example, run as written beside a ``psmini synth jute --out synthetic`` folder (a
    capture has no ``sample.mask``; its ground truth has its own): it prints the figures of ``psmini evaluate``."""
    import json

    from psmini.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(["synth", "jute", "--out", "synthetic", "--size", "96"]) == 0
    capsys.readouterr()
    code = _readme_python_blocks()[1]
    exec(compile(code, "README.md", "exec"), {})  # noqa: S102 (the README's own example)
    printed = capsys.readouterr().out.strip()
    assert main(["evaluate", "synthetic/jute", "--json"]) == 0
    evaluated = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed == (f"{evaluated['mean_angular_error_deg']:.2f}° mean angular error, "
                       f"{evaluated['depth_rmse_mm'] * 1000:.0f} µm depth RMSE")
    assert 0 < evaluated["mean_angular_error_deg"] < 5
