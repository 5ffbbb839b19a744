"""Every Python code block of the documentation runs, so the pages cannot go stale.

Every page under `docs/` is collected, and every fenced block whose language is `python` or
`py` is code. The blocks of a page run in order in one namespace (a page reads like one
script, as a reader would paste it), in a temporary working directory. Other fences (`bash`,
`text`, ...) are not code. Two kinds of Python blocks do not run here:

* blocks that include a file (`--8<-- "examples/x.py"`): the example scripts, run by
  `tests/test_docs.py`;
* blocks preceded, on the line just above the fence, by the visible marker
  `<!-- not run: REASON -->`, for code that must not run in a test process (a cluster's
  runtime, a process-wide setting). `NOT_RUN` lists them, so that a new one is noticed.

All pages run in this one module, so solves that several pages share (the same term, solver
and output) compile once. The pages in `LONG_PAGES` are marked `long`: `make test` leaves them
out, and `make docs` runs them after building the site, so that CI (which runs both) runs every
block once.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[1] / "docs"
# A fence of column 0 whose language is python or py, up to the next closing fence; group 1
# is the line just above it (for the not-run marker), group 2 the code.
FENCE = re.compile(
    r"(?:^([^\n]*)\n)?^```(?:python|py)(?:[ \t][^\n]*)?\n(.*?)^```[ \t]*$", re.S | re.M
)
# Any opening fence of a Python-like language, indented or not.
ANY_PYTHON_FENCE = re.compile(r"^[ \t]*```(?:python3?|py|pycon)\b", re.M | re.I)
NOT_RUN_MARK = re.compile(r"^<!-- not run: (\S[^\n]*?) -->[ \t]*$")

# (page, index of the Python block on the page, counting from 1) of every block marked not run.
NOT_RUN = {
    ("how-to/choosing.md", 7),  # sets JAX's persistent cache directory for the whole process
    ("how-to/choosing.md", 8),  # compile_loops_whole: XLA_FLAGS, read once per process
    ("how-to/ensembles.md", 4),  # jax.distributed.initialize needs a cluster's coordinator
    ("how-to/scaling-out.md", 2),  # starts a Dask cluster (tests/test_bench_executor.py does)
    ("how-to/scaling-out.md", 3),  # needs a Slurm cluster
    ("how-to/scaling-out.md", 4),  # needs the other processes of a jax.distributed run
}


def fenced_python(page: Path) -> list[tuple[str, str | None]]:
    """`(code, reason)` of every Python block of `page`; `reason` is None for a block that
    runs, else the reason of its not-run marker. Include blocks are left out."""
    out = []
    for above, code in FENCE.findall(page.read_text(encoding="utf-8")):
        if code.lstrip().startswith("--8<--"):
            continue
        mark = NOT_RUN_MARK.match(above or "")
        out.append((code, mark.group(1) if mark else None))
    return out


def python_blocks(page: Path) -> list[str]:
    """The blocks of `page` that run, in order."""
    return [code for code, reason in fenced_python(page) if reason is None]


PAGES = sorted(p for p in DOCS.rglob("*.md") if fenced_python(p))

# Each page compiles its own solves (together about 4 minutes of one core of the 2-core CI
# machine). The pages below, about 2 minutes of it, are marked `long`: `make test` leaves them out
# and `make docs` runs them after building the site, so CI runs every block once.
LONG_PAGES = {
    "how-to/gradients.md": "reverse-mode gradient of a solve: the costliest compile",
    "how-to/ensembles.md": "three vmapped programs (ensemble, sharded ensemble, manual sharding)",
    "how-to/choosing.md": "a solve of each of the solvers it compares",
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


def test_every_python_fence_is_seen():
    """No Python block escapes the parser (an indented fence, another spelling of the
    language), and the blocks marked not run are exactly those of `NOT_RUN`, each with a
    reason."""
    not_run = set()
    for page in sorted(DOCS.rglob("*.md")):
        name = page.relative_to(DOCS).as_posix()
        text = page.read_text(encoding="utf-8")
        seen = len(ANY_PYTHON_FENCE.findall(text))
        assert len(FENCE.findall(text)) == seen, f"docs/{name}: a Python fence the parser misses"
        marked = [i for i, (_, why) in enumerate(fenced_python(page), start=1) if why]
        # a marker that is not directly above a Python fence (or has no reason) marks nothing
        assert text.count("<!-- not run") == len(marked), f"docs/{name}: a stray not-run marker"
        not_run.update((name, i) for i in marked)
    assert not_run == NOT_RUN


def test_fence_parser_sees_blocks_and_skips_includes(tmp_path):
    page = tmp_path / "p.md"
    page.write_text(
        "text\n```python\nx = 1\n```\n\n```bash\nls\n```\n"
        '```python title="q.py"\n--8<-- "examples/q.py"\n```\n```py\ny = x + 1\n```\n'
        "<!-- not run: needs a cluster -->\n```python\nimport cluster\n```\n"
    )
    assert python_blocks(page) == ["x = 1\n", "y = x + 1\n"]
    assert fenced_python(page)[-1] == ("import cluster\n", "needs a cluster")


def test_long_pages_exist():
    names = {p.relative_to(DOCS).as_posix() for p in PAGES}
    assert set(LONG_PAGES) <= names


@pytest.mark.parametrize("page", [_param(p) for p in PAGES])
def test_page_examples_run(page, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__docs_example__"}
    for i, (block, reason) in enumerate(fenced_python(page), start=1):
        if reason is not None:
            continue
        name = f"{page.relative_to(DOCS).as_posix()} (python block {i})"
        exec(compile(block, name, "exec"), namespace)  # noqa: S102 - our own documentation
