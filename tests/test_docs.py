"""The documentation site: strict build, complete API reference, offline assets, and a look at
the built pages in headless Chromium.

The site is built once per run (`mkdocs build --strict` into a temporary folder). The browser
test serves it on 127.0.0.1, opens the home page and the solver's API page in Debian's
`chromium`, checks that the API entries and the typeset mathematics are in the rendered DOM, and
saves a screenshot of each page under `$PYTEST_ARTIFACTS` (default `tests/artifacts/`). It is
skipped, saying so, only when chromium is not installed; `make docs` (and so CI) installs it.
"""

from __future__ import annotations

import functools
import html.parser
import http.server
import importlib
import inspect
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import types
from pathlib import Path

import pytest

import diffrax_vi as dvi

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
CHROMIUM = shutil.which("chromium") or (
    "/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None
)
ENTRY = re.compile(r"^::: *([\w.]+)\s*$", re.M)


# -- building ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    try:
        import mkdocs  # noqa: F401
        import mkdocstrings  # noqa: F401
    except ImportError as err:  # a missing extra is a set-up error, not a reason to skip
        pytest.fail(f"the docs extra is not installed ({err}); pip install -e '.[docs]'")
    out = tmp_path_factory.mktemp("site")
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, f"mkdocs build --strict failed:\n{proc.stdout}\n{proc.stderr}"
    return out


def api_entries() -> dict[str, str]:
    """`{identifier: API page}` for every `::: identifier` in `docs/api/`."""
    entries = {}
    for page in sorted((DOCS / "api").glob("*.md")):
        for ident in ENTRY.findall(page.read_text(encoding="utf-8")):
            entries[ident] = page.stem
    return entries


def resolve(identifier: str):
    """Attribute `c` of module `a.b` for `a.b.c` (what a user reaches by that name, also
    where a function shadows its module, as `diffrax_vi.ensemble`), else module `a.b.c`."""
    module, _, name = identifier.rpartition(".")
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError):
        return importlib.import_module(identifier)


def test_every_public_object_has_an_api_entry(site):
    entries = api_entries()
    by_object = {}
    for ident in entries:
        by_object.setdefault(id(resolve(ident)), ident)
    missing = [name for name in dir(dvi) if id(getattr(dvi, name)) not in by_object]
    assert not missing, f"public objects without a `:::` entry in docs/api/: {missing}"
    # ... and each entry made it into the built page, under its identifier.
    for ident, page in entries.items():
        text = (site / "api" / f"{page}.html").read_text(encoding="utf-8")
        assert f'id="{ident}"' in text, f"{ident} is missing from the built api/{page}.html"
        # object.__init__'s docstring must not stand in for a class's own words.
        assert "Initialize self" not in text, f"api/{page}.html shows object.__init__'s docstring"


def own_docstring(obj) -> str | None:
    if isinstance(obj, type):
        doc = obj.__dict__.get("__doc__")
        # dataclasses (and so equinox Modules) invent `Name(field, ...)` when there is none.
        if doc and doc.startswith(f"{obj.__name__}("):
            return None
        return doc
    return getattr(obj, "__doc__", None)


@pytest.mark.parametrize("name", sorted(dir(dvi)))
def test_every_public_object_has_its_own_docstring(name):
    obj = getattr(dvi, name)
    doc = own_docstring(obj)
    assert doc and len(doc.strip()) >= 10, f"diffrax_vi.{name} has no docstring of its own"
    if isinstance(obj, types.FunctionType | type):
        assert inspect.getdoc(obj) == inspect.cleandoc(doc)


def test_docstring_check_can_fail():
    import equinox as eqx

    class Bare(eqx.Module):
        x: int

    assert own_docstring(Bare) is None
    assert own_docstring(dvi.NetworkVI)


def test_every_page_is_built_and_in_the_nav(site):
    pages = sorted(p.relative_to(DOCS).with_suffix(".html") for p in DOCS.rglob("*.md"))
    assert len(pages) >= 20
    for page in pages:
        assert (site / page).is_file(), f"{page} was not built"
    nav = (site / "index.html").read_text(encoding="utf-8")
    for must in ("Concepts", "How-to guides", "Benchmarks", "Differences", "Changelog"):
        assert must in nav


class _Tags(html.parser.HTMLParser):
    """Collects the URLs that a browser would fetch: script, link, img, iframe, source."""

    ATTRS = {"script": "src", "link": "href", "img": "src", "iframe": "src", "source": "src"}

    def __init__(self):
        super().__init__()
        self.urls: list[tuple[str, str]] = []

    def handle_starttag(self, tag, attrs):
        want = self.ATTRS.get(tag)
        for key, value in attrs:
            if key == want and value:
                self.urls.append((tag, value))


def external(url: str) -> bool:
    return bool(re.match(r"^(https?:)?//", url.strip(), re.I))


def test_external_url_detection():
    parser = _Tags()
    parser.feed(
        '<script src="https://cdn.example/x.js"></script><link href="//fonts.x/css">'
        '<a href="https://github.com/x">ok</a><img src="figures/a.png">'
    )
    assert [u for _, u in parser.urls if external(u)] == [
        "https://cdn.example/x.js",
        "//fonts.x/css",
    ]


def test_no_external_resources(site):
    """Everything a page loads ships with the site: it works offline (no CDN, no web fonts)."""
    offenders = []
    for page in site.rglob("*.html"):
        parser = _Tags()
        parser.feed(page.read_text(encoding="utf-8"))
        offenders += [f"{page.relative_to(site)}: <{t}> {u}" for t, u in parser.urls if external(u)]
    for sheet in site.rglob("*.css"):
        for url in re.findall(r"url\(\s*['\"]?([^'\")]+)", sheet.read_text(encoding="utf-8")):
            if external(url):
                offenders.append(f"{sheet.relative_to(site)}: url({url})")
    assert not offenders, "external resources:\n" + "\n".join(offenders)
    # The math renderer is the vendored copy, with its fonts.
    katex = site / "assets" / "katex"
    for asset in ("katex.min.js", "katex.min.css", "contrib/auto-render.min.js"):
        assert (katex / asset).is_file(), asset
    css = (katex / "katex.min.css").read_text(encoding="utf-8")
    for font in re.findall(r"url\((fonts/[^)]+)\)", css):
        assert (katex / font).is_file(), f"katex.min.css needs {font}"


def test_examples_page_shows_the_script_and_its_figure(site):
    text = re.sub(r"<[^>]+>", "", (site / "examples.html").read_text(encoding="utf-8"))
    assert "def long_run" in text  # the snippet include pulled in examples/quickstart.py
    assert (site / "figures" / "quickstart.png").is_file()


@pytest.mark.long
def test_example_script_runs(tmp_path):
    """The example the Examples page shows runs as shown (about 75 s of CPU: `make test-long`)."""
    out = tmp_path / "quickstart.png"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "quickstart.py"), "--out", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Harmonic oscillator to t = 200" in proc.stdout
    assert out.is_file() and out.stat().st_size > 10_000


@pytest.mark.slow
def test_the_swing_up_example_converges_in_its_documented_iterations():
    """The example of the Forces and constraints page converges as the page says: from zero
    torque, 150 Adam iterations take the loss from 9.9 to below 1e-5 (slow: `make test-slow`)."""
    import runpy

    example = runpy.run_path(str(ROOT / "examples" / "swing_up.py"))
    assert example["ITERATIONS"] == 150
    amplitudes, history = example["tune"]()
    assert history[0] > 9.0
    assert float(example["loss"](amplitudes)) < 1e-5


# -- the browser -------------------------------------------------------------------------------


def artifacts_dir() -> Path:
    path = Path(os.environ.get("PYTEST_ARTIFACTS", ROOT / "tests" / "artifacts"))
    path.mkdir(parents=True, exist_ok=True)
    return path


@pytest.fixture(scope="module")
def served(site):
    handler = functools.partial(_QuietHandler, directory=str(site))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


def chromium(*args: str) -> subprocess.CompletedProcess:
    with tempfile.TemporaryDirectory() as profile:
        return subprocess.run(
            [
                CHROMIUM,
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--no-first-run",
                f"--user-data-dir={profile}",
                "--virtual-time-budget=15000",
                "--window-size=1280,1400",
                *args,
            ],
            capture_output=True,
            text=True,
            timeout=180,
        )


def screenshot_is_a_page(path: Path) -> None:
    import matplotlib.image

    image = matplotlib.image.imread(path)
    assert image.shape[0] >= 600 and image.shape[1] >= 1000, image.shape
    # A blank or error page is nearly one colour; a rendered page has text and a header.
    assert float(image[..., :3].std()) > 0.05


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (make docs installs it)")
@pytest.mark.parametrize(
    "page, expected",
    [
        ("index.html", ["Quickstart", "Where to go next", "Concepts"]),
        (
            "api/solver.html",
            [
                'id="diffrax_vi.NetworkVI"',
                'id="diffrax_vi.ShallowNet"',
                'id="diffrax_vi.NetworkVIState"',
                "doc-signature",
            ],
        ),
    ],
    ids=["home", "api-solver"],
)
def test_pages_render_in_chromium(served, page, expected):
    url = f"{served}/{page}"
    dom = chromium("--dump-dom", url)
    assert dom.returncode == 0, dom.stderr[-2000:]
    text = dom.stdout
    for needle in expected:
        assert needle in text, f"{needle!r} not in the rendered DOM of {page}"
    # KaTeX ran: the arithmatex spans now hold typeset math, with no error nodes.
    assert text.count('class="katex"') >= 1, f"no typeset math in {page}"
    assert "katex-error" not in text
    shot = artifacts_dir() / f"docs-{page.replace('/', '-').removesuffix('.html')}.png"
    shot.unlink(missing_ok=True)
    proc = chromium(f"--screenshot={shot}", url)
    assert proc.returncode == 0 and shot.is_file(), proc.stderr[-2000:]
    screenshot_is_a_page(shot)


def test_layout_module_table_covers_the_package():
    """Every module of the package is named in the module table of `docs/layout.md` (a
    folder named there covers the modules in it), and every path the table names exists."""
    root = Path(__file__).resolve().parents[1]
    text = (root / "docs" / "layout.md").read_text(encoding="utf-8")
    cited = set(re.findall(r"`(diffrax_vi/[\w/.]*)`", text))
    assert cited, "the scan finds the table"
    missing = []
    for path in sorted((root / "diffrax_vi").rglob("*.py")):
        name = path.relative_to(root).as_posix()
        if path.name == "__init__.py" and path.parent != root / "diffrax_vi":
            name = path.parent.relative_to(root).as_posix() + "/"
        if name not in cited and not any(
            c.endswith("/") and name.startswith(c) for c in cited
        ):
            missing.append(name)
    assert missing == [], f"modules missing from the module table of docs/layout.md: {missing}"
    assert [c for c in cited if not (root / c).exists()] == []
