"""Every Python code block of the documentation runs, so the pages cannot go stale.

The blocks of a page run in order in one namespace (a page reads like one script), in a
temporary working directory. Blocks that include a file (`--8<-- "examples/x.py"`) are the
example scripts, run by `tests/test_docs.py`. All pages run in this one module, so solves that
several pages share (the same term, solver and output) compile once. The pages in
`LONG_PAGES` are marked `long` (run by `make test-long`) to keep CI within its time budget.
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

# Each page compiles its own solves (about 20 s of CPU each on the CI machine). These pages run
# in `make test-long`; the others, which cover the quickstart, the problem library, dense
# output and events and degenerate terms, run in `make test` and CI.
LONG_PAGES = {
    "how-to/gradients.md": "reverse-mode gradient of a solve: the costliest compile",
    "how-to/ensembles.md": "a vmapped solve (the tests of the solver cover vmap too)",
    "how-to/lagrangians.md": "another user Lagrangian (the Home quickstart runs one in CI)",
    "how-to/precision.md": "float32 solve, the configuration of test_solver's float32 test",
    "getting-started.md": "the oscillator solve again (the Home quickstart runs one in CI)",
}


def _param(page: Path):
    name = page.relative_to(DOCS).as_posix()
    marks = [pytest.mark.long] if name in LONG_PAGES else []
    return pytest.param(page, marks=marks, id=name)


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


def test_long_pages_exist():
    names = {p.relative_to(DOCS).as_posix() for p in PAGES}
    assert set(LONG_PAGES) <= names


@pytest.mark.parametrize("page", [_param(p) for p in PAGES])
def test_page_examples_run(page, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__docs_example__"}
    for i, block in enumerate(python_blocks(page)):
        name = f"{page.relative_to(DOCS).as_posix()} (python block {i + 1})"
        exec(compile(block, name, "exec"), namespace)  # noqa: S102 - our own documentation
