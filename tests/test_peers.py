"""heyoka as an optional peer (`diffrax_vi.bench.peers`, the `peers` extra): the Hamiltonian's
translation, the peer's accuracy, the ensemble runners, the harness entry, the error without
heyoka and a smoke run of `python -m benchmarks.peers_side_by_side --quick`.

The tests that run heyoka skip when it is not installed (CI installs `.[test,docs]` only)."""

from __future__ import annotations

import math
import sys

import diffrax
import jax.numpy as jnp
import numpy as np
import pytest

from diffrax_vi import problems
from diffrax_vi.bench import Heyoka, hamilton, peers, work_precision


def _kepler(orbits=1.0):
    return problems.kepler(0.5, t1=2 * math.pi * orbits, dtype=jnp.float64)


# -- without heyoka ------------------------------------------------------------------------------
def test_only_the_peer_module_imports_heyoka_and_only_when_asked():
    """No module of the package imports heyoka but `bench/peers.py`, and that one inside a
    function (a static check: the other tests of this process may have imported it)."""
    import ast
    from pathlib import Path

    package = Path(peers.__file__).resolve().parents[1]
    found = []
    for path in sorted(package.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        top = set(tree.body)
        for node in ast.walk(tree):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            if any(n.split(".")[0] == "heyoka" for n in names):
                found.append((path.name, node in top))
            if isinstance(node, ast.Call) and any(
                    isinstance(a, ast.Constant) and a.value == "heyoka" for a in node.args):
                func = node.func
                called = func.attr if isinstance(func, ast.Attribute) else \
                    getattr(func, "id", "")
                if called in ("import_module", "__import__", "find_spec"):
                    found.append((path.name, False))
    assert found and all(name == "peers.py" and not top_level
                         for name, top_level in found), found


def test_missing_heyoka_names_the_peers_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "heyoka", None)  # `import heyoka` raises ImportError
    for call in (peers.require_heyoka, lambda: peers.HeyokaPeer(_kepler(), 1e-12)):
        with pytest.raises(ImportError, match=r"diffrax_vi\[peers\]") as info:
            call()
        assert "`peers` extra" in str(info.value)
    # in the harness, a row that says so (the sweep goes on)
    (row,) = work_precision(_kepler(), [Heyoka()], rtols=[1e-9], repeats=1)
    assert row["status"] == "error:ImportError" and "peers" in row["message"]


@pytest.mark.parametrize("make", [_kepler, lambda: problems.henon_heiles(dtype=jnp.float64),
                                  lambda: problems.toda_lattice(dtype=jnp.float64)])
def test_hamilton_equations_from_the_traced_hamiltonian_match_the_term(make):
    """The Hamiltonian's jaxpr evaluated on sympy symbols, differentiated: the term's own
    vector field at y0 (slices, sums, concatenations and nested jits translated)."""
    problem = make()
    t, qs, ps, H, rhs = hamilton.hamilton_equations(problem)
    assert len(rhs) == 2 * problem.dim
    hamilton.check_equations(problem, t, qs, ps, rhs)  # raises where they differ
    if problem.name == "kepler":
        import sympy as sp

        assert sp.simplify(rhs[2] + qs[0] / (qs[0]**2 + qs[1]**2) ** sp.Rational(3, 2)) == 0


def test_a_degenerate_problem_is_refused_by_name():
    """The reference's pendulum is linear in the velocities: no Hamilton equations in the
    term's (q, p); the check says so instead of integrating something else."""
    problem = problems.pendulum(dtype=jnp.float64)
    t, qs, ps, _, rhs = hamilton.hamilton_equations(problem)
    with pytest.raises(ValueError, match="pendulum: Hamilton's equations"):
        hamilton.check_equations(problem, t, qs, ps, rhs)


# -- with heyoka ---------------------------------------------------------------------------------
def test_kepler_peer_reaches_the_exact_solution():
    pytest.importorskip("heyoka")
    peer = peers.HeyokaPeer(_kepler(), 1e-15)
    run = peer.timed_run(repeats=2)
    assert run.outcome == "time_limit" and run.steps > 10
    assert run.position_error < 1e-10 and run.state_error < 1e-10
    assert 0 < run.wall_s <= run.median_s and run.runs == 2 and peer.compile_s > 0
    # step ends of one run: every one on the energy shell
    ts, q, p, _ = peer.step_ends()
    assert ts[0] == 0.0 and math.isclose(ts[-1], 2 * math.pi) and len(ts) == run.steps + 1
    energy = 0.5 * np.sum(p**2, axis=1) - 1 / np.linalg.norm(q, axis=1)
    assert np.max(np.abs(energy + 0.5)) < 1e-12


def test_extended_precision_peer_agrees_with_the_stored_henon_heiles_reference():
    hy = pytest.importorskip("heyoka")
    problem = problems.henon_heiles(dtype=jnp.float64)  # stored reference over (0, 10)
    run = peers.HeyokaPeer(problem, 1e-19, fp_type=np.longdouble).timed_run(repeats=1,
                                                                              warmup=0)
    assert run.q.dtype == np.longdouble and run.state_error < 2e-15
    assert hy is not None


def test_kepler_ensemble_runners_return_every_member_finite():
    pytest.importorskip("heyoka")
    out = peers.kepler_ensemble(6, orbits=1, tol=1e-12, methods=("loop", "ensemble", "batch"),
                                repeats=1)
    assert set(out) == {"loop", "ensemble", "batch"}
    for method, run in out.items():
        assert run["states"].shape == (6, 4) and np.all(np.isfinite(run["states"])), method
        assert run["max_error"] < 1e-9 and run["member_orbits_per_s"] > 0
    np.testing.assert_allclose(out["loop"]["states"], out["ensemble"]["states"], rtol=0,
                               atol=1e-15)


def test_heyoka_in_the_work_precision_harness():
    pytest.importorskip("heyoka")
    rows = work_precision(_kepler(), [Heyoka()], rtols=[1e-9, 1e-15], repeats=2)
    assert [r["status"] for r in rows] == ["ok", "ok"]
    assert rows[1]["error"] < 1e-12 < rows[0]["error"] < 1e-7
    assert rows[1]["energy_error"] < 1e-13 and rows[1]["family"] == "peer"
    assert rows[0]["compile_s"] > 0 and rows[0]["wall_s"] > 0


def test_side_by_side_script_quick(monkeypatch, capsys, tmp_path):
    """`--quick` end to end, with a cheap stand-in for CGVI (its compilation alone takes
    longer than this test may)."""
    pytest.importorskip("heyoka")
    import diffrax_vi as dvi
    from benchmarks import peers_side_by_side as script

    monkeypatch.setattr(dvi, "CGVI", lambda degree: diffrax.Euler())  # runs on the term
    out = tmp_path / "table.txt"
    script.main(["--quick", "--repeats", "1", "--out", str(out)])
    text = capsys.readouterr().out
    assert out.read_text() == text
    for phrase in ("heyoka (order 15)", "tol 1e-15", "CGVI(6)", "Dopri8",
                   "heyoka batch (SIMD, 1 core)", "heyoka ensemble (2 threads)",
                   "vmap CGVI(6)", "long double tol 1e-19 differs by",
                   "Kepler, heyoka tol 1e-12", "Henon-Heiles, heyoka tol 1e-15"):
        assert phrase in text, phrase
