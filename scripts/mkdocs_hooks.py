"""mkdocs hooks: the home page is the README; the benchmarks page shows the latest run of every benchmark.

``benchmarks/results.md`` is the ledger: each benchmark script appends a dated section (``## title``) at its end,
so one benchmark may have several sections. At build time the marker ``<!-- latest-benchmarks -->`` in
``docs/benchmarks.md`` is replaced by the last section of each title, in the order the titles first appear, so
the site never holds a copy of a figure that the ledger does not.
"""

from __future__ import annotations

import re
from pathlib import Path

MARKER = "<!-- latest-benchmarks -->"
README_MARKER = "<!-- readme -->"
ROOT = Path(__file__).resolve().parents[1]
LEDGER = ROOT / "benchmarks" / "results.md"


def latest_sections(text: str) -> list[tuple[str, str]]:
    """``(title, body)`` of the last section of each ``## title`` in ``text``, in order of first appearance."""
    parts = re.split(r"^## (.+)$", text, flags=re.MULTILINE)
    latest: dict[str, str] = {}
    for title, body in zip(parts[1::2], parts[2::2], strict=True):
        latest[title.strip()] = body.strip()
    order = list(dict.fromkeys(t.strip() for t in parts[1::2]))
    return [(title, latest[title]) for title in order]


def on_files(files, config):  # noqa: ARG001 (mkdocs hook signature)
    """Publish the ledger's pictures (e.g. ``focus_curves.png``) under ``benchmarks/`` of the site."""
    from mkdocs.structure.files import File

    for picture in sorted(LEDGER.parent.glob("*.png")):
        files.append(File(f"benchmarks/{picture.name}", str(ROOT), config["site_dir"], config["use_directory_urls"]))
    return files


def on_page_markdown(markdown: str, page, config, files) -> str:  # noqa: ARG001 (mkdocs hook signature)
    if README_MARKER in markdown:
        # the front page is the README, its links into docs/ made relative to the site
        readme = (ROOT / "README.md").read_text(encoding="utf-8")
        return markdown.replace(README_MARKER, readme.replace("](docs/", "]("))
    if MARKER not in markdown:
        return markdown
    sections = latest_sections(LEDGER.read_text(encoding="utf-8"))
    # the ledger's own headings become level-2 headings of the page; deeper ones move down with them
    rendered = "\n\n".join(f"## {title}\n\n{body}" for title, body in sections)
    # pictures beside the ledger are published under benchmarks/ (on_files)
    rendered = re.sub(r"\]\(([\w.-]+\.png)\)", r"](benchmarks/\1)", rendered)
    # links from the ledger into docs/ (figures in docs/gallery/) are relative to benchmarks/: the page sits in docs/
    rendered = rendered.replace("](../docs/", "](")
    return markdown.replace(MARKER, rendered)
