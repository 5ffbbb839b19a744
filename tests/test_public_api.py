"""The public boundary: `dir(diffrax_vi)` is `__all__`, every public name resolves, and the API
pages (`::: identifier` blocks in docs/api/) list exactly the public names of the package and of
its public subpackages `oga` and `problems`."""

from __future__ import annotations

import re
import types
from pathlib import Path

import diffrax_vi as dvi
from diffrax_vi import oga, problems

DOCS_API = Path(__file__).resolve().parents[1] / "docs" / "api"
ENTRY = re.compile(r"^::: *([\w.]+)\s*$", re.M)
# The benchmark harness is a public subpackage of its own, documented on its own page.
OWN_PAGES = {"bench.md"}
SUBPACKAGES = {"oga": oga, "problems": problems}


def _public(names) -> list[str]:
    return sorted(n for n in names if not n.startswith("_"))


def _documented() -> list[str]:
    found = []
    for page in sorted(DOCS_API.glob("*.md")):
        if page.name not in OWN_PAGES:
            found += ENTRY.findall(page.read_text(encoding="utf-8"))
    return found


def test_dir_is_all():
    assert _public(dir(dvi)) == sorted(dvi.__all__)
    assert len(set(dvi.__all__)) == len(dvi.__all__)
    for name, module in SUBPACKAGES.items():
        assert _public(dir(module)) == sorted(module.__all__), name


def test_every_public_name_resolves():
    for name in dvi.__all__:
        assert getattr(dvi, name) is not None, name
    for module in SUBPACKAGES.values():
        for name in module.__all__:
            assert getattr(module, name) is not None, name


def test_no_public_object_outside_all():
    """Every public, non-module attribute the package binds is in `__all__`."""
    for module in (dvi, *SUBPACKAGES.values()):
        bound = {
            n
            for n, v in vars(module).items()
            if not n.startswith("_") and not isinstance(v, types.ModuleType)
        }
        assert bound <= set(module.__all__), (module.__name__, bound - set(module.__all__))


def test_the_api_pages_list_exactly_the_public_names():
    documented = _documented()
    assert len(documented) == len(set(documented)), "an identifier is documented twice"
    top = {i.removeprefix("diffrax_vi.") for i in documented if i.count(".") == 1}
    assert top == set(dvi.__all__)
    for name, module in SUBPACKAGES.items():
        prefix = f"diffrax_vi.{name}."
        listed = {i.removeprefix(prefix) for i in documented if i.startswith(prefix)}
        assert listed == set(module.__all__), name
    others = [
        i for i in documented if i.count(".") > 1 and i.split(".")[1] not in SUBPACKAGES
    ]
    assert others == [], "API entries under internal module paths"


def test_oga_numerics_are_private():
    for name in ("qr_append", "lu_solve", "jacobi_svd", "guarded_solve", "QRState"):
        assert name not in oga.__all__ and name not in dir(oga)
