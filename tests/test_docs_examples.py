"""Every Python code block of the documentation runs, so the pages cannot go stale.

The blocks of a page run in order in one namespace (a page reads like one script), in a
temporary working directory. Blocks that include a file (`--8<-- "examples/x.py"`) are the
example scripts, run by `tests/test_docs.py`. All pages run in this one module, so solves that
several pages share (the same term, solver and output) compile once.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[1] / "docs"
FENCE = re.compile(r"^```python[^\n]*\n(.*?)^```[ \t]*$", re.S | re.M)


def python_blocks(page: Path) -> list[str]:
    blocks = FENCE.findall(page.read_text(encoding="utf-8"))
    return [b for b in blocks if not b.lstrip().startswith("--8<--")]


PAGES = sorted(p for p in DOCS.rglob("*.md") if python_blocks(p))


def test_the_pages_have_examples():
    names = {p.relative_to(DOCS).as_posix() for p in PAGES}
    # The pages whose point is code; a page losing its examples should be noticed.
    for page in (
        "index.md",
        "getting-started.md",
        "how-to/lagrangians.md",
        "how-to/degenerate.md",
        "how-to/dense-output.md",
        "how-to/ensembles.md",
        "how-to/gradients.md",
        "how-to/precision.md",
    ):
        assert page in names, f"docs/{page} has no Python example"


def test_fence_parser_sees_blocks_and_skips_includes(tmp_path):
    page = tmp_path / "p.md"
    page.write_text(
        "text\n```python\nx = 1\n```\n\n```bash\nls\n```\n"
        '```python title="q.py"\n--8<-- "examples/q.py"\n```\n```python\ny = x + 1\n```\n'
    )
    assert python_blocks(page) == ["x = 1\n", "y = x + 1\n"]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(DOCS).as_posix())
def test_page_examples_run(page, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__docs_example__"}
    for i, block in enumerate(python_blocks(page)):
        name = f"{page.relative_to(DOCS).as_posix()} (python block {i + 1})"
        exec(compile(block, name, "exec"), namespace)  # noqa: S102 - our own documentation
