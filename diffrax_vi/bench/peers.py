"""heyoka, the Taylor integrator, as an optional peer of the benchmarks, timed in our process.

heyoka (`pip install "diffrax_vi[peers]"`, or `pip install heyoka`) is imported only here and
only when a peer is built: the package itself never imports it, and a missing heyoka is an
`ImportError` that names the `peers` extra.

Hamilton's equations are written for heyoka from the problem itself, not from a table: sympy
derives them from the problem's JAX Hamiltonian (`diffrax_vi.bench.hamilton`, checked against
the term's vector field), and they become heyoka expressions here (`heyoka_system`). Every
problem of `diffrax_vi.problems` translates; `HeyokaPeer(system=...)` takes hand-written heyoka
equations instead.

- `HeyokaPeer(problem, tol)`: one `heyoka.taylor_adaptive`, built (and compiled by LLVM)
  once, its build time kept apart in `compile_s`; `propagate`, `timed_run` (best and median
  of N runs, final state, error against a reference), `step_ends`, `propagate_many` (a loop
  over one integrator, `ensemble_propagate_until` on threads, or heyoka's SIMD batch mode).
- `kepler_ensemble`: N Kepler orbits (eccentricities spread over an interval), member-orbits
  per second and the largest position error against the exact solutions.
- `heyoka_run`: one work-precision point for `harness.work_precision` (the `Heyoka` entry).
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import math
import statistics
import time
from collections.abc import Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np

from .hamilton import check_equations, hamilton_equations

__all__ = [
    "heyoka_available",
    "require_heyoka",
    "heyoka_system",
    "HeyokaPeer",
    "PeerRun",
    "EnsembleRun",
    "kepler_members",
    "kepler_ensemble",
    "heyoka_run",
    "MISSING_MESSAGE",
]

MISSING_MESSAGE = (
    "the heyoka peer needs heyoka, which is an optional dependency: install the `peers` extra "
    "(pip install 'diffrax_vi[peers]') or heyoka itself (pip install heyoka)"
)


def heyoka_available() -> bool:
    """Whether heyoka can be imported (found on the path; nothing is imported)."""
    return importlib.util.find_spec("heyoka") is not None


def require_heyoka():
    """The `heyoka` module, imported now; an `ImportError` naming the `peers` extra if it is
    not installed."""
    try:
        return importlib.import_module("heyoka")
    except ImportError as e:
        raise ImportError(MISSING_MESSAGE) from e


# -- Hamilton's equations as heyoka expressions ------------------------------------------------
def _fp_name(fp_type) -> str:
    if fp_type is float or fp_type is np.float64:
        return "float64"
    if fp_type is np.longdouble:
        return "long double"
    return getattr(fp_type, "__name__", str(fp_type))


def _convert(fp_type, x):
    """A float64 (or int) value in heyoka's `fp_type`, exactly."""
    hy = require_heyoka()
    if fp_type is float or fp_type is np.float64:
        return float(x)
    if fp_type is np.longdouble:
        return np.longdouble(x)
    if fp_type is hy.real128:
        return hy.real128(repr(float(x))) if isinstance(x, float | np.floating) \
            else hy.real128(str(x))
    raise ValueError(f"unsupported fp_type {fp_type!r}: float, np.longdouble or heyoka.real128")


def _rational_constant(fp_type, r):
    """The sympy rational `r` as a heyoka number of `fp_type` (rounded once where it is not a
    number of that type)."""
    hy = require_heyoka()
    if fp_type is float or fp_type is np.float64:
        return hy.expression(float(r))
    if fp_type is np.longdouble:
        value = np.longdouble(str(r.p)) / np.longdouble(str(r.q))
    else:
        value = hy.real128(str(r.p)) / hy.real128(str(r.q))
    return hy.expression(value)


def _functions() -> dict:
    hy = require_heyoka()
    import sympy as sp

    table = {getattr(sp, name): getattr(hy, name)
             for name in ("sin", "cos", "tan", "asin", "acos", "atan", "atan2", "sinh", "cosh",
                          "tanh", "asinh", "acosh", "atanh", "exp", "log", "erf", "erfc")}
    return table


def _power(base, n: int):
    """`base**n` for an integer `n >= 2` by squares and products: heyoka's Taylor recurrence
    for a general power divides by the base, so `x**3` fails where `x` starts at 0."""
    if n == 1:
        return base
    if n % 2:
        return _power(base, n - 1) * base
    half = _power(base, n // 2)
    return half**2 if n == 2 else (half * half)


def _to_heyoka(expr, mapping: dict, cache: dict):
    """The sympy expression `expr` as a heyoka expression; `mapping` gives the symbols and
    the numbers that are not float64 numbers."""
    hy = require_heyoka()
    if expr in mapping:
        return mapping[expr]
    key = id(expr)
    if key in cache:
        return cache[key][1]
    if expr.is_Number:
        out = hy.expression(float(expr))  # exact: other numbers are in `mapping`
    elif expr.is_Add:
        out = hy.sum([_to_heyoka(a, mapping, cache) for a in expr.args])
    elif expr.is_Mul:
        out = hy.prod([_to_heyoka(a, mapping, cache) for a in expr.args])
    elif expr.is_Pow:
        base = _to_heyoka(expr.base, mapping, cache)
        exponent = expr.exp
        if exponent.is_Integer and int(exponent) >= 2:
            out = _power(base, int(exponent))
        elif exponent.is_Number and exponent in mapping:
            out = base ** mapping[exponent]
        elif exponent.is_Number:
            out = base ** float(exponent)
        else:
            out = base ** _to_heyoka(exponent, mapping, cache)
    else:
        fn = _functions().get(type(expr))
        if fn is None:
            raise NotImplementedError(f"no heyoka function for the sympy {type(expr).__name__}"
                                      f" in {expr}")
        out = fn(*(_to_heyoka(a, mapping, cache) for a in expr.args))
    cache[key] = (expr, out)  # keep expr alive so that its id stays unique
    return out


def heyoka_system(problem, fp_type=float, *, check: bool = True):
    """`[(variable, expression), ...]` for `heyoka.taylor_adaptive`: Hamilton's equations of
    `problem` (state `concat(q, p)`), constants held in `fp_type` (`float`, `np.longdouble`
    or `heyoka.real128`). `check`: compare them with the term's vector field at `y0` first."""
    hy = require_heyoka()
    import sympy as sp

    t, qs, ps, _, rhs = hamilton_equations(problem)
    if check:
        check_equations(problem, t, qs, ps, rhs)
    names = [f"q{i}" for i in range(len(qs))] + [f"p{i}" for i in range(len(ps))]
    variables = hy.make_vars(*names)
    variables = list(variables) if isinstance(variables, list | tuple) else [variables]
    mapping: dict = dict(zip((*qs, *ps), variables, strict=True))
    mapping[t] = hy.time
    for expr in rhs:
        for r in expr.atoms(sp.Rational):
            dyadic = r.q & (r.q - 1) == 0
            if r in mapping or dyadic and abs(r.p).bit_length() <= 53:
                continue  # a float64 number: converted exactly
            mapping[r] = _rational_constant(fp_type, r)
    cache: dict = {}
    return [(v, _to_heyoka(expr, mapping, cache))
            for v, expr in zip(variables, rhs, strict=True)]


# -- the peer ----------------------------------------------------------------------------------
@dataclasses.dataclass
class PeerRun:
    """One timed propagation of a `HeyokaPeer`.

    `q`, `p`: the final state (float64 arrays, or the peer's type); `wall_s`: best of the timed
    runs; `median_s`: their median; `runs`; `compile_s`: the integrator's build (decomposition
    and LLVM compilation, once per peer); `steps`: Taylor steps of the last run; `outcome`:
    heyoka's outcome name (`time_limit` when it reached `t1`); `position_error` and
    `state_error`: max-norm of `q − q_ref` and of `(q, p) − (q_ref, p_ref)` where a reference
    was given (else `None`)."""

    t1: float
    q: np.ndarray
    p: np.ndarray
    wall_s: float
    median_s: float
    runs: int
    compile_s: float
    steps: int
    outcome: str
    position_error: float | None = None
    state_error: float | None = None


@dataclasses.dataclass
class EnsembleRun:
    """Many members propagated by one `HeyokaPeer`: `method` (`loop`, `ensemble`, `batch`),
    `members`, `wall_s` (best) and `median_s` of the timed runs, `states` (members × 2D),
    `threads`."""

    method: str
    members: int
    wall_s: float
    median_s: float
    runs: int
    states: np.ndarray
    threads: int = 1


def _best_and_median(times: Sequence[float]) -> tuple[float, float]:
    return min(times), statistics.median(times)


class HeyokaPeer:
    """heyoka's adaptive Taylor integrator on a `Problem`'s Hamilton equations.

    **Arguments:**

    - `problem`: a `diffrax_vi.problems` problem (its Hamiltonian is translated, see the
      module's docstring); its `y0`, `t0` and `t1` are the defaults of the runs.
    - `tol`: heyoka's tolerance (relative and absolute; it also sets the Taylor order).
    - `fp_type`: `float` (default), `np.longdouble` or `heyoka.real128`.
    - `system`: hand-written `[(variable, expression), ...]` instead of the translation
      (state order `concat(q, p)`).
    - `compact_mode`, `high_accuracy`: heyoka's options of those names.
    - `check`: compare the translated equations with the term's vector field at `y0`.
    - `cold_compile`: build without heyoka's caches of compiled code (in memory and on disk,
      `~/.cache/heyoka`), so that `compile_s` is a first compilation, as JAX's is without a
      persistent cache; `False` lets heyoka reuse what it compiled before.

    The integrator is built once, in the constructor; `compile_s` is that time (the
    translation to heyoka expressions excluded, in `translate_s`)."""

    def __init__(self, problem, tol: float, *, fp_type=float, system=None,
                 compact_mode: bool = False, high_accuracy: bool = False, check: bool = True,
                 cold_compile: bool = True):
        hy = require_heyoka()
        if not (tol > 0):
            raise ValueError(f"tol must be positive, got {tol!r}")
        self.hy = hy
        self.problem = problem
        self.tol = tol
        self.fp_type = fp_type
        start = time.perf_counter()
        if system is None:
            system = heyoka_system(problem, fp_type, check=check)
        self.translate_s = time.perf_counter() - start
        self.y0 = np.concatenate([np.asarray(x, np.float64) for x in problem.y0])
        state = [_convert(fp_type, x) for x in self.y0]
        kwargs = dict(tol=_convert(fp_type, tol), compact_mode=compact_mode,
                      high_accuracy=high_accuracy)
        if fp_type is not float and fp_type is not np.float64:
            kwargs["fp_type"] = fp_type
        self.system = system
        self._kwargs = kwargs
        cache = hy.llvm_state
        enabled = cache.get_diskcache_enabled()
        if cold_compile:  # heyoka keeps compiled code in memory and on disk (~/.cache/heyoka)
            cache.set_diskcache_enabled(False)
            cache.clear_memcache()
        try:
            start = time.perf_counter()
            self.ta = hy.taylor_adaptive(system, state, time=_convert(fp_type, problem.t0),
                                         **kwargs)
            self.compile_s = time.perf_counter() - start
        finally:
            cache.set_diskcache_enabled(enabled)
        self.order = self.ta.order
        self.dim = problem.dim

    def __repr__(self) -> str:
        return (f"HeyokaPeer({self.problem.name}, tol={self.tol:g}, "
                f"{_fp_name(self.fp_type)}, order {self.order})")

    # -- single runs --------------------------------------------------------------------------
    def _reset(self, y0=None, t0=None):
        y0 = self.y0 if y0 is None else np.asarray(y0, np.float64).ravel()
        self.ta.time = _convert(self.fp_type, self.problem.t0 if t0 is None else t0)
        self.ta.state[:] = [_convert(self.fp_type, x) for x in y0] \
            if self.fp_type is not float else y0

    def propagate(self, t1: float | None = None, y0=None, *, callback=None):
        """From `y0` (flat `concat(q, p)`, default the problem's) at `t0` to `t1` (default the
        problem's). Returns heyoka's result tuple; the state is in `self.ta.state`."""
        self._reset(y0)
        t1 = self.problem.t1 if t1 is None else t1
        kwargs = {} if callback is None else dict(callback=callback)
        return self.ta.propagate_until(_convert(self.fp_type, t1), **kwargs)

    def state(self) -> np.ndarray:
        """The integrator's current state, as float64 (`np.longdouble` for extended types)."""
        s = self.ta.state
        if self.fp_type is float:
            return np.array(s, np.float64)
        return np.array([np.longdouble(str(x)) for x in s], dtype=np.longdouble)

    def timed_run(self, t1: float | None = None, *, repeats: int = 5, warmup: int = 1,
                  reference: tuple[np.ndarray, np.ndarray] | bool | None = None,
                  budget_s: float = math.inf) -> PeerRun:
        """`warmup` untimed runs, then `repeats` timed ones (fewer when they exceed
        `budget_s`): best and median wall time, the final state, and its error against
        `reference = (q_ref, p_ref)` (`None`: the problem's reference when it has one;
        `False`: no error)."""
        t1 = self.problem.t1 if t1 is None else float(t1)
        for _ in range(warmup):
            self.propagate(t1)
        times = []
        res = None
        for _ in range(max(repeats, 1)):
            start = time.perf_counter()
            res = self.propagate(t1)
            times.append(time.perf_counter() - start)
            if sum(times) > budget_s:
                break
        best, median = _best_and_median(times)
        y = self.state()
        d = self.dim
        run = PeerRun(t1=t1, q=y[:d], p=y[d:], wall_s=best, median_s=median, runs=len(times),
                      compile_s=self.compile_s, steps=int(res[3]), outcome=res[0].name)
        if reference is None and self.problem.reference_flow is not None:
            reference = self.problem.reference(np.array([t1]))
            reference = (reference[0][0], reference[1][0])
        if reference is not None and reference is not False:
            q_ref, p_ref = (np.asarray(x) for x in reference)
            run.position_error = float(np.max(np.abs(run.q - q_ref)))
            run.state_error = float(max(run.position_error, np.max(np.abs(run.p - p_ref))))
        return run

    def step_ends(self, t1: float | None = None, y0=None):
        """`(ts, q, p, result)` at every step end of one run (untimed: a Python callback
        records them), float64."""
        rec_t, rec_y = [float(self.problem.t0)], [None]

        def record(ta):
            rec_t.append(float(ta.time))
            rec_y.append(np.array(ta.state, np.float64))
            return True

        self._reset(y0)
        rec_y[0] = np.array(self.ta.state, np.float64)
        res = self.propagate(t1, y0, callback=record)
        ys = np.stack(rec_y)
        d = self.dim
        return np.asarray(rec_t), ys[:, :d], ys[:, d:], res

    # -- many members -------------------------------------------------------------------------
    def propagate_many(self, y0s: np.ndarray, t1: float, *, method: str = "loop",
                       threads: int = 2, repeats: int = 3, warmup: int = 1) -> EnsembleRun:
        """Every row of `y0s` (members × 2D, float64) from `t0` to `t1`, timed (best and median
        of `repeats` after `warmup`), by

        - `"loop"`: one integrator, its time and state reset per member (one core);
        - `"ensemble"`: `heyoka.ensemble_propagate_until` on `threads` threads (each member
          gets a copy of the integrator, as heyoka does it);
        - `"batch"`: a `taylor_adaptive_batch` of heyoka's recommended SIMD width, looped
          over chunks of members (one core; built here, its build not timed)."""
        if self.fp_type is not float:
            raise ValueError("propagate_many runs float64 peers only")
        y0s = np.asarray(y0s, np.float64)
        n = y0s.shape[0]
        hy = self.hy
        t0 = float(self.problem.t0)
        t1 = float(t1)
        if method == "loop":
            ta = self.ta

            def run():
                out = np.empty_like(y0s)
                for i in range(n):
                    ta.time = t0
                    ta.state[:] = y0s[i]
                    ta.propagate_until(t1)
                    out[i] = ta.state
                return out
        elif method == "ensemble":
            def gen(ta, i):
                ta.time = t0
                ta.state[:] = y0s[i]
                return ta

            def run():
                results = hy.ensemble_propagate_until(self.ta, t1, n, gen,
                                                      algorithm="thread", max_workers=threads)
                return np.stack([np.array(r[0].state) for r in results])
        elif method == "batch":
            width = hy.recommended_simd_size()
            tb = hy.taylor_adaptive_batch(self.system, np.tile(self.y0[:, None], (1, width)),
                                          **self._kwargs)

            def run():
                out = np.empty_like(y0s)
                for start in range(0, n, width):
                    chunk = y0s[start:start + width]
                    block = np.tile(self.y0[:, None], (1, width))
                    block[:, :len(chunk)] = chunk.T
                    tb.set_time(t0)
                    tb.state[:] = block
                    tb.propagate_until(t1)
                    out[start:start + len(chunk)] = tb.state[:, :len(chunk)].T
                return out
        else:
            raise ValueError(f"method must be 'loop', 'ensemble' or 'batch', got {method!r}")
        for _ in range(warmup):
            states = run()
        times = []
        for _ in range(max(repeats, 1)):
            start = time.perf_counter()
            states = run()
            times.append(time.perf_counter() - start)
        best, median = _best_and_median(times)
        return EnsembleRun(method=method, members=n, wall_s=best, median_s=median,
                           runs=len(times), states=states,
                           threads=threads if method == "ensemble" else 1)


# -- the Kepler ensemble -------------------------------------------------------------------------
def kepler_members(members: int, eccentricities: tuple[float, float] = (0.1, 0.6)):
    """`(e, y0s)`: `members` eccentricities evenly spread over the closed interval and their
    perihelion states `concat(q0, p0)` (members × 4), as `problems.kepler` starts them."""
    e = np.linspace(eccentricities[0], eccentricities[1], members)
    y0s = np.zeros((members, 4))
    y0s[:, 0] = 1 - e
    y0s[:, 3] = np.sqrt((1 + e) / (1 - e))
    return e, y0s


def kepler_positions(e: np.ndarray, t1: float) -> np.ndarray:
    """The exact positions (members × 2) at `t1` of the members of eccentricities `e`."""
    from ..problems import kepler

    return np.stack([kepler(float(x), dtype=jnp.float64).reference(np.array([t1]))[0][0]
                     for x in e])


def kepler_ensemble(members: int = 256, orbits: float = 10, tol: float = 1e-15, *,
                    methods: Sequence[str] = ("loop", "ensemble"), threads: int = 2,
                    repeats: int = 3, eccentricities=(0.1, 0.6)) -> dict[str, dict[str, Any]]:
    """heyoka on `members` Kepler orbits (eccentricities over `eccentricities`, `orbits`
    periods of 2π each), by each of `methods` (see `HeyokaPeer.propagate_many`). Per method:
    `wall_s`, `median_s`, `member_orbits_per_s`, `max_error` (largest position error, max
    norm, against the exact solutions), `compile_s` (the one integrator's build), `states`."""
    from ..problems import kepler

    t1 = 2 * math.pi * orbits
    peer = HeyokaPeer(kepler(0.5, t1=t1, dtype=jnp.float64), tol)
    e, y0s = kepler_members(members, eccentricities)
    exact = kepler_positions(e, t1)
    out = {}
    for method in methods:
        run = peer.propagate_many(y0s, t1, method=method, threads=threads, repeats=repeats)
        out[method] = dict(
            wall_s=run.wall_s, median_s=run.median_s, runs=run.runs, threads=run.threads,
            member_orbits_per_s=members * orbits / run.wall_s,
            max_error=float(np.max(np.abs(run.states[:, :2] - exact))),
            compile_s=peer.compile_s, states=run.states,
        )
    return out


# -- the harness's work-precision point ----------------------------------------------------------
_PEER_CACHE: dict[tuple, HeyokaPeer] = {}


def heyoka_run(problem, entry, t1: float, tol: float, repeats: int, budget_s: float):
    """One point of `harness.work_precision` for a `Heyoka` entry: `(ts, q, p, row)` with the
    step ends of an untimed run (for the energy error) and the row's fields (`status`,
    `steps`, `wall_s` median of the timed runs, `compile_s`, `repeats`). Peers are kept per
    (problem, tol, options), so repeated sweeps build each integrator once."""
    key = (id(problem), float(tol), entry.compact_mode, entry.high_accuracy)
    peer = _PEER_CACHE.get(key)
    compile_s = 0.0
    if peer is None or peer.problem is not problem:
        peer = HeyokaPeer(problem, tol, compact_mode=entry.compact_mode,
                          high_accuracy=entry.high_accuracy)
        _PEER_CACHE.clear()  # one problem at a time: integrators hold compiled code
        _PEER_CACHE[key] = peer
        compile_s = peer.compile_s
    run = peer.timed_run(t1, repeats=repeats, warmup=1, reference=False, budget_s=budget_s)
    ts, q, p, res = peer.step_ends(t1)
    finite = bool(np.all(np.isfinite(q)) and np.all(np.isfinite(p)))
    outcome = res[0].name
    if not finite or outcome == "err_nf_state":
        status = "nonfinite"
    else:
        status = "ok" if outcome == "time_limit" else f"error:heyoka_{outcome}"
    row = dict(status=status, steps=int(res[3]),
               rejected=None, wall_s=run.median_s, compile_s=compile_s, repeats=run.runs)
    return ts, q, p, row
