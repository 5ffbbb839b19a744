"""Issue 31: does a network ansatz win anywhere? Hard problems at large steps, against fair
baselines at equal work.

For each hard problem (Kepler at e = 0.9 and 0.99, Hénon–Heiles on its chaotic default orbit,
the modulated-frequency oscillator, the charged particle in a non-uniform magnetic field and
Fermi–Pasta–Ulam) every configuration runs on
constant steps from well below the motion's shortest time scale up to several times it:

- the linear front: `CGVI(s)` over degrees and steps (a smaller step is CGVI with sub-steps;
  the report names the degree `SpectralCGVI` would choose at each step);
- `NetworkVI` configurations: a shallow network (activation, width, Gauss–Legendre nodes) with
  its hidden layer fixed (`UniformLayer`, the default), taken from the first step's seed fit
  and then frozen (`FirstSeedLayer`), fitted on every step (`SeedLayer`), or solved for with
  the rest of the parameters (the reference's all-parameter `FreeEndpoints()` step);
- classical peers: diffrax `Dopri8` and `Tsit5` under a PID controller at tight tolerances.

The runs are made by the long-run study's engine (`diffrax_vi.bench.long_run.run_study`: one
compilation per solver and problem, median wall time of repeats after compilation, final
error against an extended-precision or stored reference, largest energy error at step ends,
failed solves recorded with their status). This script adds the configurations, the degrees
of freedom per step, the fronts and the 3x verdict:

- a configuration's front is its Pareto front of (wall time, final error) over the `ok` runs;
- the ratio at equal wall time is the largest `error_baseline(w) / error_config(w)`, and the
  ratio at equal error the largest `time_baseline(e) / time_config(e)`, both log-log
  interpolated on the two fronts where their ranges overlap; past the baseline's last run
  (more time than its slowest, more error than its cheapest) that run bounds the baseline
  and the ratio is an upper bound, which never makes a win; errors below `FLOOR` count as
  `FLOOR`, and at equal wall time the baseline gets `SLACK` times the time (timing noise);
- a solve that reports success with an error above the solution's size is `escaped`;
- a network configuration "wins" against a baseline where either ratio is at least 3. The
  baselines: the linear front (all CGVI runs together), the frozen twin (for the adaptive
  configurations: the `UniformLayer` and `FirstSeedLayer` runs of the same activation, width
  and quadrature together, so that the adaptivity itself is measured against the better
  frozen layer), and the classical peers (for information).

    .venv/bin/python -m benchmarks.hard_problems [--quick | --full] [--out DIR]
        [--problems ...] [--report-only]

`--full` adds activations (tanh, gelu, sigmoid) and widths (6, 10 on 8 Gauss nodes, 16 on
16), CGVI degrees 2 to 16, seven steps per problem, six tolerances and five repeats.

Results (`--out`, default `benchmarks/results/hard_problems/`): `runs.csv` (one row per run),
`verdict.csv` (the ratios), `report.md`, and per problem `<problem>_fronts.png` (final
and energy error against wall time) and `<problem>_dof.png` (final error against degrees of
freedom per step at the largest steps). The engine's rows, the reference and the run time of
each problem are kept in `raw/`, so that `--problems` reruns a subset and the report
(`--report-only` rebuilds it) still covers every problem run.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import platform
import shutil
import tempfile
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402
from diffrax_vi.bench import Adaptive, read_rows, write_rows  # noqa: E402
from diffrax_vi.bench.long_run import LongRunProblem, code_version, run_study  # noqa: E402
from diffrax_vi.bench.report import markdown, pyplot  # noqa: E402
from diffrax_vi.spectral import DEFAULT_MAX_DEGREE, spectral_degree  # noqa: E402

from .common import RESULTS, command_line  # noqa: E402

DEFAULT_OUT = RESULTS / "hard_problems"
WIN = 3.0
"""The factor a network configuration must beat a baseline by (issue 31)."""
SAVES = 64
"""Saved times per run: the energy error is the largest at these step ends."""
ESCAPED = 1.0
"""A run that reports success with a final error or an energy error above this (relative: the
size of the solution) is recorded as `escaped`, not as a point of its front."""
FLOOR = 1e-12
"""Final errors below this count as this in the ratios: near round-off, the errors of two
runs differ by their rounding, not by their method."""
SLACK = 1.25
"""The ratio at equal wall time gives the baseline this factor more time: medians of a few
runs of milliseconds on a shared core differ by that much, and on a steep front a small
difference of time is a large one of error."""


# -- problems ------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class HardProblem:
    """One problem of the study.

    - `constructor`: the name of its function in `diffrax_vi.problems`.
    - `kwargs`: the constructor's arguments.
    - `period`, `unit`: the time unit of the span and of the steps (steps per `period`).
    - `periods`: the span in `period`s; each run ends 1/8 `period` later.
    - `timescale`: the motion's shortest time scale (`1/ω` of the fastest oscillation, the
      pericentre passage `r_p / v_p` of an orbit): the steps reach a few times it.
    - `quick_steps`, `full_steps`: steps per `period`.
    - `reference_step`: step of the extended-precision GBS reference (`None`: the problem's
      closed form or stored reference).
    - `energy_conserved`: whether `|H − H₀|` measures an error (not for the time-dependent
      modulated oscillator).
    """

    constructor: str
    kwargs: Mapping[str, Any]
    period: float
    unit: str
    periods: int
    timescale: float
    quick_steps: tuple[float, ...]
    full_steps: tuple[float, ...]
    reference_step: float | None = None
    atol_ratio: float = 1.0
    energy_conserved: bool = True
    note: str = ""

    def make(self):
        return getattr(problems, self.constructor)(dtype=jnp.float64, **self.kwargs)

    def engine(self, full: bool) -> LongRunProblem:
        steps = self.full_steps if full else self.quick_steps
        return LongRunProblem(self.make, self.period, self.unit, (self.periods,),
                              (self.periods,), steps, (), atol_ratio=self.atol_ratio,
                              reference_step=self.reference_step)


def pericentre_time(eccentricity: float) -> float:
    """`r_p / v_p` of a Kepler orbit of semi-major axis 1 and period 2π."""
    return (1 - eccentricity) ** 1.5 / math.sqrt(1 + eccentricity)


TWO_PI = 2 * math.pi
PROBLEMS: dict[str, HardProblem] = {
    "kepler_e0.9": HardProblem(
        "kepler", {"eccentricity": 0.9}, TWO_PI, "orbits (2π)", 1, pericentre_time(0.9),
        (50, 100, 200, 400, 800), (25, 50, 100, 200, 400, 800, 1600),
        note="starts at pericentre; the span holds two pericentre passages"),
    "kepler_e0.99": HardProblem(
        "kepler", {"eccentricity": 0.99}, TWO_PI, "orbits (2π)", 1, pericentre_time(0.99),
        (500, 1000, 2000, 4000, 8000), (250, 500, 1000, 2000, 4000, 8000, 16000),
        note="starts at pericentre; the span holds two pericentre passages"),
    "henon_heiles": HardProblem(
        "henon_heiles", {}, TWO_PI, "linear periods (2π)", 20, 1.0,
        (2, 4, 8, 16, 32), (1.5, 2, 3, 4, 8, 16, 32, 64), reference_step=0.05,
        note="the default orbit, H₀ = 0.135 (chaotic)"),
    "modulated_oscillator": HardProblem(
        "modulated_oscillator", {}, TWO_PI / 0.1, "modulation periods (2π/ν)", 2, 1 / 1.5,
        (16, 32, 64, 128, 256), (8, 16, 32, 64, 128, 256, 512), reference_step=0.1,
        energy_conserved=False,
        note="ω(t) between 0.5 and 1.5; the energy is not conserved (its column is no error)"),
    "charged_particle": HardProblem(
        "charged_particle", {}, TWO_PI / 8.0, "gyrations (2π/8)", 40, 1 / 8.0,
        (1, 2, 4, 8, 16), (0.5, 1, 2, 4, 8, 16, 32),
        note="B = 8 at the start, 8.9 at the guiding centre: gyration period 0.70 to 0.79"),
    "fermi_pasta_ulam": HardProblem(
        "fermi_pasta_ulam", {}, TWO_PI / 50.0, "fast periods (2π/ω)", 40, 1 / 50.0,
        (1, 2, 4, 8, 16), (0.5, 1, 2, 4, 8, 16, 32),
        note="ω = 50: the stiff springs' period is 0.126; the span holds 40 of them"),
}


# -- configurations ------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Config:
    """One constant-step solver of the study.

    - `family`: `"linear"` (CGVI), `"frozen"` (a network whose hidden layer does not move
      along the run after the first step) or `"adaptive"` (a hidden layer fitted or solved
      for on every step).
    - `dof`: the parameters per coordinate that choose the step's curve: the trial space's
      dimension for a linear span (`s + 1` for `CGVI(s)`, the kept directions of the
      projected span), plus the `2·width` hidden parameters where each step fits them, or
      all `3·width` for the all-parameter step.
    - `twin`: for a network, its activation, width and quadrature (the key of its frozen
      twin); `""` for CGVI.
    - `hidden`: how the hidden layer is chosen (`"uniform"`, `"first seed"`, `"seed"`,
      `"all-parameter"`), `""` for CGVI.
    """

    name: str
    family: str
    make: Callable[[], diffrax.AbstractSolver]
    dof: int
    twin: str = ""
    hidden: str = ""


ACTIVATIONS = {"tanh": dvi.tanh, "gelu": dvi.gelu, "sigmoid": dvi.sigmoid}
HIDDEN = ("uniform", "first seed", "seed", "all-parameter")


def cgvi(degree: int) -> Config:
    return Config(f"CGVI({degree})", "linear", lambda: dvi.CGVI(degree), degree + 1)


def network(activation: str, width: int, nodes: int, hidden: str) -> Config:
    """A `NetworkVI` of `ShallowNetBasis(activation, width)` and `GaussLegendre(nodes)` whose
    hidden layer is chosen by `hidden` (one of `HIDDEN`)."""
    act = ACTIVATIONS[activation]
    basis = dvi.ShallowNetBasis(act, width)
    rank = min(width, nodes + 1)  # VariableProjection's default
    formulation, dof, family = {
        "uniform": (lambda: dvi.VariableProjection(hidden=dvi.UniformLayer()), rank, "frozen"),
        "first seed": (lambda: dvi.VariableProjection(hidden=dvi.FirstSeedLayer()), rank,
                       "frozen"),
        "seed": (lambda: dvi.VariableProjection(hidden=dvi.SeedLayer()), rank + 2 * width,
                 "adaptive"),
        "all-parameter": (lambda: dvi.FreeEndpoints(), 3 * width, "adaptive"),
    }[hidden]
    twin = f"{activation} {width}, GL{nodes}"
    return Config(f"{twin}, {hidden}", family,
                  lambda: dvi.NetworkVI(basis, dvi.GaussLegendre(nodes),
                                        formulation=formulation()),
                  dof, twin, hidden)


QUICK_DEGREES = (6, 8, 12)
FULL_DEGREES = (2, 3, 4, 6, 8, 10, 12, 16)
QUICK_NETWORKS = (("tanh", 10, 8),)
FULL_NETWORKS = tuple((a, w, n) for a in ACTIVATIONS for w, n in ((6, 8), (10, 8), (16, 16)))
QUICK_RTOLS = (1e-8, 1e-11, 1e-14)
FULL_RTOLS = (1e-6, 1e-8, 1e-10, 1e-12, 1e-13, 1e-14)


def configurations(full: bool = False) -> list[Config]:
    """The constant-step solvers of the quick or full study."""
    out = [cgvi(s) for s in (FULL_DEGREES if full else QUICK_DEGREES)]
    for a, w, n in FULL_NETWORKS if full else QUICK_NETWORKS:
        out += [network(a, w, n, h) for h in HIDDEN]
    return out


def peers() -> tuple[Adaptive, ...]:
    return (Adaptive("Dopri8", diffrax.Dopri8(), atol_ratio=1.0),
            Adaptive("Tsit5", diffrax.Tsit5(), atol_ratio=1.0))


# -- fronts and ratios ---------------------------------------------------------------------------
def ok_rows(rows: Iterable[Mapping], key: str = "error") -> list[Mapping]:
    """The runs that count: status `ok`, a positive wall time and a positive `key`."""
    return [r for r in rows if r.get("status") == "ok" and _positive(r.get("wall_s"))
            and _positive(r.get(key))]


def _positive(x) -> bool:
    return isinstance(x, int | float) and math.isfinite(x) and x > 0


def front(rows: Iterable[Mapping], key: str = "error",
          floor: float = 0.0) -> list[tuple[float, float]]:
    """The Pareto front `(wall, key)` of the runs that count: cheapest first, each point more
    accurate than every cheaper one (values below `floor` count as `floor`)."""
    out: list[tuple[float, float]] = []
    for wall, err in sorted((r["wall_s"], max(r[key], floor)) for r in ok_rows(rows, key)):
        if not out or err < out[-1][1]:
            out.append((wall, err))
    return out


def _interp(xs: Sequence[float], ys: Sequence[float], x: float) -> float | None:
    """Log-log interpolation of the points `(xs, ys)` (`xs` increasing) at `x`; `None`
    outside their range."""
    if not xs or x < xs[0] * (1 - 1e-12) or x > xs[-1] * (1 + 1e-12):
        return None
    if len(xs) == 1:
        return ys[0]
    for (x0, y0), (x1, y1) in zip(zip(xs, ys, strict=True), zip(xs[1:], ys[1:], strict=True),
                                  strict=True):
        if x0 <= x <= x1 or math.isclose(x, x0) or math.isclose(x, x1):
            if x1 == x0:
                return min(y0, y1)
            s = (math.log(x) - math.log(x0)) / (math.log(x1) - math.log(x0))
            s = min(max(s, 0.0), 1.0)
            return math.exp(math.log(y0) + s * (math.log(y1) - math.log(y0)))
    return None


def error_ratio(config: Sequence[tuple[float, float]],
                baseline: Sequence[tuple[float, float]],
                slack: float = 1.0) -> tuple[float, float, bool] | None:
    """The largest `error_baseline(slack·w) / error_config(w)` over the wall times `w` (the
    points of both fronts) of the configuration's range, the `w` where it is reached, and
    whether it is exact: where the configuration runs longer than the baseline's most
    expensive run, the baseline's error there bounds its error, and the ratio is an upper
    bound. `None` where the configuration's runs are all cheaper than the baseline's."""
    return _best_ratio(config, [(w / slack, e) for w, e in baseline], by_error=False)


def time_ratio(config: Sequence[tuple[float, float]],
               baseline: Sequence[tuple[float, float]]) -> tuple[float, float, bool] | None:
    """The largest `time_baseline(e) / time_config(e)` over the errors `e` (the points of both
    fronts) of the configuration's range, the `e` where it is reached, and whether it is
    exact: where the configuration's error is larger than that of the baseline's cheapest
    run, that run's time bounds the baseline's, and the ratio is an upper bound. `None` where
    the configuration is more accurate than every run of the baseline."""
    return _best_ratio(config, baseline, by_error=True)


def _best_ratio(config, baseline, *, by_error: bool):
    if not config or not baseline:
        return None
    if by_error:  # time as a function of error: errors increasing
        c = sorted((e, w) for w, e in config)
        b = sorted((e, w) for w, e in baseline)
    else:
        c, b = list(config), list(baseline)
    cx, cy = [p[0] for p in c], [p[1] for p in c]
    bx, by = [p[0] for p in b], [p[1] for p in b]
    best = None
    for x in sorted(set(cx) | set(bx)):
        yc, yb, exact = _interp(cx, cy, x), _interp(bx, by, x), True
        if yc is not None and yb is None and x > bx[-1]:
            # past the baseline's last point (more time than its most expensive run, or more
            # error than its cheapest): it does at least as well as there
            yb, exact = by[-1], False
        if yc is None or yb is None:
            continue
        ratio = yb / yc
        if best is None or ratio > best[0]:
            best = (ratio, x, exact)
    return best


def verdicts(rows: Sequence[Mapping], configs: Mapping[str, Config], *, floor: float = FLOOR,
             slack: float = SLACK) -> list[dict[str, Any]]:
    """Per problem and network configuration: its ratios (at equal wall time, at equal error;
    `floor`, `slack`: see `FLOOR`, `SLACK`) against the linear front, its frozen twin and the
    classical peers, and whether it wins (a ratio of at least `WIN`)."""
    out = []
    for problem in dict.fromkeys(r["problem"] for r in rows):
        rs = [r for r in rows if r["problem"] == problem]
        linear = front((r for r in rs if _family(r, configs) == "linear"), floor=floor)
        classical = front((r for r in rs if _family(r, configs) == "peer"), floor=floor)
        for name in dict.fromkeys(r["solver"] for r in rs):
            cfg = configs.get(name)
            if cfg is None or cfg.family == "linear":
                continue
            mine = front((r for r in rs if r["solver"] == name), floor=floor)
            good = ok_rows(r for r in rs if r["solver"] == name)
            row: dict[str, Any] = dict(problem=problem, solver=name, family=cfg.family,
                                       dof=cfg.dof, ok=len(good),
                                       runs=sum(r["solver"] == name for r in rs),
                                       best_error=min((r["error"] for r in good), default=None))
            baselines = {"linear": linear, "peers": classical}
            if cfg.family == "adaptive":
                baselines["twin"] = front(
                    (r for r in rs if (c := configs.get(r["solver"])) is not None
                     and c.twin == cfg.twin and c.family == "frozen"), floor=floor)
            for label, base in baselines.items():
                at_time, at_error = error_ratio(mine, base, slack), time_ratio(mine, base)
                row[f"{label}_error_ratio"] = at_time[0] if at_time else None
                row[f"{label}_error_ratio_at_s"] = at_time[1] if at_time else None
                row[f"{label}_error_ratio_exact"] = at_time[2] if at_time else None
                row[f"{label}_time_ratio"] = at_error[0] if at_error else None
                row[f"{label}_time_ratio_at_error"] = at_error[1] if at_error else None
                row[f"{label}_time_ratio_exact"] = at_error[2] if at_error else None
                ratios = [x[0] for x in (at_time, at_error) if x]
                row[f"{label}_best"] = max(ratios) if ratios else None
                # a win needs a measured ratio; a bound of WIN or more leaves it open
                row[f"{label}_wins"] = any(x[0] >= WIN and x[2] for x in (at_time, at_error)
                                           if x)
                row[f"{label}_open"] = not row[f"{label}_wins"] and any(
                    x[0] >= WIN for x in (at_time, at_error) if x)
            row["wins"] = row["linear_wins"] and row.get("twin_wins", True) and (
                cfg.family == "adaptive")
            out.append(row)
    return out


def _family(row: Mapping, configs: Mapping[str, Config]) -> str:
    cfg = configs.get(row["solver"])
    return "peer" if cfg is None else cfg.family


# -- running -------------------------------------------------------------------------------------
def run_problem(name: str, hard: HardProblem, configs: Sequence[Config], out: str, *,
                full: bool, rtols: Sequence[float] | None = None, repeats: int | None = None,
                budget_s: float | None = None, max_run_s: float | None = None,
                peer_entries: Sequence[Adaptive] | None = None,
                saves: int = SAVES) -> list[dict[str, Any]]:
    """Run one problem through the long-run engine; its rows and reference are kept in
    `out/raw/<name>.csv` and `out/raw/<name>_reference.csv`."""
    raw = os.path.join(out, "raw")
    os.makedirs(raw, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        rows = run_study(
            tmp, problems={name: hard.engine(full)}, spans={name: (hard.periods,)}, full=full,
            solvers={c.name: c.make for c in configs}, saves=saves,
            peers=peers() if peer_entries is None else tuple(peer_entries),
            rtols=rtols or (FULL_RTOLS if full else QUICK_RTOLS),
            repeats=repeats or (5 if full else 3), budget_s=budget_s or (6.0 if full else 2.0),
            max_run_s=max_run_s or (300.0 if full else 60.0),
            reference_budget_s=600.0 if full else 120.0)
        shutil.copy(os.path.join(tmp, "long_run.csv"), os.path.join(raw, f"{name}.csv"))
        shutil.copy(os.path.join(tmp, "references.csv"),
                    os.path.join(raw, f"{name}_reference.csv"))
    return rows


def annotate(rows: Iterable[Mapping], configs: Mapping[str, Config],
             hards: Mapping[str, HardProblem]) -> list[dict[str, Any]]:
    """The engine's rows with the study's columns: family, dof per step, twin, step size in
    units of the time scale."""
    out = []
    for r in rows:
        cfg = configs.get(r["solver"])
        hard = hards.get(r["problem"])
        row = dict(r)
        row.update(family="peer" if cfg is None else cfg.family,
                   dof=None if cfg is None else cfg.dof,
                   twin="" if cfg is None else cfg.twin,
                   hidden="" if cfg is None else cfg.hidden)
        dt = r.get("dt")
        if hard is not None and _positive(dt):
            row["dt_over_timescale"] = dt / hard.timescale
        elif hard is not None and _positive(r.get("steps")) and _positive(r.get("t1")):
            row["dt_over_timescale"] = r["t1"] / r["steps"] / hard.timescale  # mean step
        if hard is not None and not hard.energy_conserved:
            row["energy_error"] = None
        if row.get("status") == "ok" and any(
                _positive(row.get(k)) and row[k] > ESCAPED for k in ("error", "energy_error")):
            row["status"] = "escaped"
            row["message"] = (f"the solve reported success, but its final error or energy "
                              f"error exceeds {ESCAPED:g}")
        out.append(row)
    return out


RUN_COLUMNS = (
    "problem", "solver", "family", "hidden", "twin", "dof", "parameter", "value",
    "steps_per_period", "dt", "dt_over_timescale", "status", "steps", "rejected", "wall_s",
    "compile_s", "repeats", "error", "energy_error", "it_mean", "it_max", "iterations",
    "ref_error", "message",
)
VERDICT_COLUMNS = (
    "problem", "solver", "family", "dof", "ok", "runs", "best_error",
    *(f"{b}_{k}" for b in ("linear", "twin", "peers") for k in (
        "error_ratio", "error_ratio_at_s", "error_ratio_exact", "time_ratio",
        "time_ratio_at_error", "time_ratio_exact", "best", "wins", "open")),
    "wins",
)


# -- report --------------------------------------------------------------------------------------
def _f(x, spec=".1e") -> str:
    if x is None or x == "" or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return format(x, spec) if isinstance(x, int | float) and not isinstance(x, bool) else str(x)


def _spectral(dt: float, timescale: float) -> str:
    try:
        return str(spectral_degree(dt, timescale))
    except ValueError:
        return f"> {DEFAULT_MAX_DEGREE}"


def plot_fronts(rows: Sequence[Mapping], problem: str, path: str, energy: bool = True) -> None:
    """Final error (and energy error) against wall time: every configuration's runs, the
    fronts drawn as lines."""
    plt = pyplot()
    keys = [("error", "final error (relative, q)")]
    if energy:
        keys.append(("energy_error", "max |H − H₀| / |H₀|"))
    fig, axes = plt.subplots(1, len(keys), figsize=(6.2 * len(keys), 4.6), squeeze=False)
    style = {"linear": ("s-", 1.2), "frozen": ("o--", 1.2), "adaptive": ("D-", 2.0),
             "peer": ("x:", 1.0)}
    rs = [r for r in rows if r["problem"] == problem]
    solvers = list(dict.fromkeys(r["solver"] for r in rs))
    many = len(solvers) > 12  # then each family's front is drawn, its members faintly
    colours = {"linear": "C0", "frozen": "C2", "adaptive": "C3", "peer": "C7"}
    for ax, (key, label) in zip(axes.flat, keys, strict=True):
        for solver in solvers:
            sel = [r for r in rs if r["solver"] == solver]
            pts = sorted((r["wall_s"], r[key]) for r in ok_rows(sel, key))
            if not pts:
                continue
            marker, lw = style.get(sel[0]["family"], ("o-", 1.0))
            if many:
                ax.loglog(*zip(*pts, strict=True), marker, lw=0.6, ms=2, alpha=0.3,
                          color=colours.get(sel[0]["family"], "k"))
            else:
                ax.loglog(*zip(*pts, strict=True), marker, lw=lw, ms=4, label=solver)
        if many:
            for family, colour in colours.items():
                fam = front((r for r in rs if r["family"] == family), key)
                if fam:
                    ax.loglog(*zip(*fam, strict=True), style[family][0], color=colour, lw=2.2,
                              ms=5, label=f"{family} (front of "
                              f"{len({r['solver'] for r in rs if r['family'] == family})})")
        ax.set_xlabel("wall time after compilation [s]")
        ax.set_ylabel(label)
        ax.set_title(f"{problem}: {label.split(' (')[0]}", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def plot_dof(rows: Sequence[Mapping], problem: str, path: str, panels: int = 3) -> None:
    """Final error against degrees of freedom per step (per coordinate) at the largest step
    sizes, one panel per step size; a failed run is drawn at the top as a cross."""
    plt = pyplot()
    rs = [r for r in rows if r["problem"] == problem and r.get("dof") is not None]
    spps = sorted({r["steps_per_period"] for r in rs if r.get("steps_per_period")})[:panels]
    if not spps:
        return
    fig, axes = plt.subplots(1, len(spps), figsize=(4.6 * len(spps), 4.2), squeeze=False)
    colours = {"linear": "C0", "frozen": "C2", "adaptive": "C3"}
    for ax, spp in zip(axes.flat, spps, strict=True):
        sel = [r for r in rs if r["steps_per_period"] == spp]
        top = max([r["error"] for r in ok_rows(sel)] + [1.0])
        for family, colour in colours.items():
            fam = [r for r in sel if r["family"] == family]
            good = sorted((r["dof"], r["error"]) for r in ok_rows(fam))
            if good:
                ax.semilogy(*zip(*good, strict=True), "o" if family != "linear" else "s-",
                            color=colour, label=family)
            bad = [r["dof"] for r in fam if r not in ok_rows(fam)]
            if bad:
                ax.semilogy(bad, [top * 3] * len(bad), "x", color=colour, ms=8)
        dt = next((r["dt_over_timescale"] for r in sel if r.get("dt_over_timescale")), None)
        ax.set_title(f"{problem}: {spp:g} steps/period (h = {_f(dt, '.2g')} time scales)",
                     fontsize=9)
        ax.set_xlabel("degrees of freedom per step and coordinate")
        ax.set_ylabel("final error (x: failed)")
        ax.grid(True, which="both", alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _problem_summary(rows, problem, hard: HardProblem | None, ref: Mapping | None) -> list[str]:
    rs = [r for r in rows if r["problem"] == problem]
    lines = [f"## {problem}", ""]
    if hard is not None:
        lines += [f"{hard.note}. Span {hard.periods} {hard.unit} + 1/8 "
                  f"(T = {_f(rs[0].get('t1'), '.4g')}), time scale {hard.timescale:.3g}.", ""]
    if ref is not None:
        lines += [f"Reference: {ref['method']}, estimated error {_f(ref.get('error'))}.", ""]
    if hard is not None:
        spps = sorted({r["steps_per_period"] for r in rs if r.get("steps_per_period")})
        lines += [markdown(["steps per period", "h", "h / time scale",
                            "degree SpectralCGVI picks"],
                           [[f"{s:g}", _f(hard.period / s, ".3g"),
                             _f(hard.period / s / hard.timescale, ".2g"),
                             _spectral(hard.period / s, hard.timescale)] for s in spps]), ""]
    lines += [f"![fronts]({problem}_fronts.png)", "", f"![dof]({problem}_dof.png)", ""]
    body = []
    for solver in dict.fromkeys(r["solver"] for r in rs):
        sel = [r for r in rs if r["solver"] == solver]
        good = ok_rows(sel)
        fr = front(sel)
        setting = (lambda r: f"{r['steps_per_period']:g}/p" if r.get("steps_per_period")
                   else f"rtol {r['value']:.0e}")
        failed = [f"{setting(r)} {r['status']}" for r in sel if r not in good]
        best = min(good, key=lambda r: r["error"], default=None)
        body.append([solver, sel[0]["family"], _f(sel[0].get("dof"), "d"),
                     f"{len(good)}/{len(sel)}", _f(best["error"] if best else None),
                     setting(best) if best else "–", _f(best["wall_s"] if best else None, ".3g"),
                     _f(min((r["energy_error"] for r in good
                             if _positive(r.get("energy_error"))), default=None)),
                     "; ".join(f"{w:.3g} s: {e:.1e}" for w, e in fr),
                     ", ".join(failed) or "–"])
    lines += [markdown(["solver", "family", "dof/step", "ok", "best error", "at", "wall s",
                        "best energy error", "front (wall: error)", "not ok"], body), ""]
    return lines


def _win_cell(v: Mapping) -> str:
    if v["wins"]:
        return "**yes**"
    if v["family"] == "adaptive" and (v["linear_open"] or v["twin_open"]) and not (
            v["linear_best"] is not None and v["linear_best"] < WIN
            or v.get("twin_best") is not None and v["twin_best"] < WIN):
        return "open (a bound of 3x or more)"
    return "vs linear front only" if v["linear_wins"] else "no"


def _verdict_table(vs: Sequence[Mapping]) -> str:
    def ratio(v, label):
        a, b = v.get(f"{label}_error_ratio"), v.get(f"{label}_time_ratio")
        if a is None and b is None:
            return "no overlap"

        def one(x, exact):
            return _f(x, ".2g") if x is None or exact else f"≤ {x:.2g}"

        return (f"{one(a, v.get(f'{label}_error_ratio_exact'))} / "
                f"{one(b, v.get(f'{label}_time_ratio_exact'))}")

    body = [[v["solver"], v["family"], f"{v['ok']}/{v['runs']}", _f(v["best_error"]),
             ratio(v, "linear"), ratio(v, "twin") if v["family"] == "adaptive" else "(is frozen)",
             ratio(v, "peers"),
             _win_cell(v)] for v in vs]
    return markdown(["configuration", "family", "ok", "best error",
                     "vs linear front: error / time ratio", "vs frozen twin", "vs Dopri8/Tsit5",
                     "3x win"], body)


def write_report(out: str, *, command: str = "", elapsed: float | None = None,
                 configs: Iterable[Config] | None = None,
                 hards: Mapping[str, HardProblem] | None = None) -> str:
    """`runs.csv`, `verdict.csv`, the figures and `report.md` from the raw files in
    `out/raw/` (`configs`, `hards`: the configurations and problems that the rows name;
    default those of the quick and full forms)."""
    hards = PROBLEMS if hards is None else hards
    raw = os.path.join(out, "raw")
    names = sorted(f[:-4] for f in os.listdir(raw) if f.endswith(".csv")
                   and not f.endswith(("_reference.csv", "_meta.csv"))
                   ) if os.path.isdir(raw) else []
    names = [n for n in hards if n in names] + [n for n in names if n not in hards]
    configs = {c.name: c for c in (configurations(True) + configurations(False)
                                   if configs is None else configs)}
    rows: list[dict[str, Any]] = []
    refs: dict[str, Mapping] = {}
    for n in names:
        rows += annotate(read_rows(os.path.join(raw, f"{n}.csv")), configs, hards)
        rp = os.path.join(raw, f"{n}_reference.csv")
        if os.path.exists(rp):
            refs[n] = read_rows(rp)[0]
    write_rows(rows, os.path.join(out, "runs.csv"), columns=RUN_COLUMNS)
    vs = verdicts(rows, configs)
    write_rows(vs, os.path.join(out, "verdict.csv"), columns=VERDICT_COLUMNS)
    parts = ["# Hard problems: where does a network ansatz win? (issue 31)", ""]
    if command:
        parts += [f"Command: `{command}`" + ("" if elapsed is not None else
                                             " (the runs' own commands: table below)"), ""]
    if elapsed is not None:
        parts += [f"Wall time of this run: {elapsed:.0f} s ({elapsed / 60:.1f} min).", ""]
    else:
        seconds = [float(read_rows(p)[0]["seconds"]) for n in names
                   if os.path.exists(p := os.path.join(raw, f"{n}_meta.csv"))]
        if seconds:
            parts += [f"Report rebuilt from `raw/`; the runs took {sum(seconds):.0f} s "
                      f"({sum(seconds) / 60:.1f} min) together, per problem below.", ""]
    parts += [
        f"Code: {code_version() or 'unknown'}. Machine: {platform.platform()}, jax "
        f"{jax.__version__} ({jax.default_backend()}), one process pinned to one core of a "
        "2-core machine that other jobs may have shared: wall times are compared within this "
        "run only.", "",
        "Final error: `max|q(T) − q_ref(T)| / max|q_ref(T)|`. Energy error: the largest "
        f"`|H − H₀|/|H₀|` at {SAVES} step ends spread over the span (every step end of a "
        "shorter run). Wall time: median of repeated runs after compilation. "
        "dof/step: parameters per coordinate that choose a step's curve (CGVI(s): s + 1; the "
        "projected network: its span's kept directions, plus 2·width hidden parameters where "
        "every step fits them; the all-parameter step: 3·width). Only `ok` runs enter the "
        "fronts; every other status is listed, among them `escaped`: a solve that reported "
        f"success with a final or energy error above {ESCAPED:g} (the orbit left).", "",
        f"Ratios (`error / time`): the largest factor by which the configuration's front beats "
        "the baseline's at equal wall time (error ratio) and at equal error (time ratio), "
        "log-log interpolated where the two fronts overlap; where the configuration runs "
        "longer than the baseline's slowest run, or less accurately than its cheapest, that "
        "run bounds the baseline and the ratio is an upper bound (`≤`; only measured ratios "
        "make a win). > 1 favours the network. Two guards against noise: errors below "
        f"{FLOOR:g} count as {FLOOR:g} "
        "(round-off: two runs there differ by their rounding), and at equal wall time the "
        f"baseline gets {SLACK:g}x the time (medians of millisecond runs on a shared core "
        "differ by that much, and on a steep front a little time is a lot of error). A "
        f"configuration wins at {WIN:g}x. Baselines: the linear front (every CGVI run of the "
        "problem, all degrees and steps); the frozen twin of an adaptive configuration (the "
        "`UniformLayer` and `FirstSeedLayer` runs of the same activation, width and "
        "quadrature, together); the classical peers (Dopri8 and Tsit5, for information).",
        "",
    ]
    metas = [read_rows(p)[0] for n in names
             if os.path.exists(p := os.path.join(raw, f"{n}_meta.csv"))]
    if metas:
        parts += ["Run time per problem (compilations included):", "",
                  markdown(["problem", "form", "runs", "not ok", "seconds", "command"],
                           [[m["problem"], m["form"], m["runs"], m["not_ok"],
                             _f(m["seconds"], ".0f"), f"`{m['command']}`"] for m in metas]),
                  ""]
    parts += ["## Verdict", ""]
    for n in names:
        sel = [v for v in vs if v["problem"] == n]
        winners = [v["solver"] for v in sel if v["wins"]]
        linear_only = [v["solver"] for v in sel if v["linear_wins"] and not v["wins"]]
        best = max(sel, key=lambda v: v.get("linear_best") or 0.0, default=None)
        text = (f"**{n}**: " + (f"a network configuration wins 3x: {', '.join(winners)}."
                                if winners else "no network configuration is 3x better than "
                                "both the linear front and its frozen twin."))
        if linear_only:
            text += (" Better than the linear front by 3x, but frozen (no adaptivity to "
                     f"credit): {', '.join(linear_only)}.")
        still_open = [v["solver"] for v in sel if _win_cell(v).startswith("open")]
        if still_open:
            text += f" Left open by bounds: {', '.join(still_open)}."
        if best is not None and best.get("linear_best") is not None:
            text += (f" Closest to the linear front: {best['solver']} "
                     f"(best ratio {best['linear_best']:.2g}).")
        parts += [text, ""]
    for n in names:
        parts += [f"### {n}", "", _verdict_table([v for v in vs if v["problem"] == n]), ""]
    for n in names:
        hard = hards.get(n)
        plot_fronts(rows, n, os.path.join(out, f"{n}_fronts.png"),
                    energy=hard is None or hard.energy_conserved)
        plot_dof(rows, n, os.path.join(out, f"{n}_dof.png"))
        parts += _problem_summary(rows, n, hard, refs.get(n))
    text = "\n".join(parts)
    with open(os.path.join(out, "report.md"), "w") as f:
        f.write(text)
    return text


# -- command line --------------------------------------------------------------------------------
def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true",
                        help="the quick form (the default; --full for the sweep of "
                             "activations, widths and degrees)")
    parser.add_argument("--full", action="store_true")
    parser.add_argument("--out", default=str(DEFAULT_OUT))
    parser.add_argument("--problems", nargs="*", default=None, choices=list(PROBLEMS))
    parser.add_argument("--report-only", action="store_true",
                        help="rebuild report.md and the figures from out/raw/")
    args = parser.parse_args(argv)
    if args.quick and args.full:
        parser.error("give --quick or --full, not both")
    os.makedirs(args.out, exist_ok=True)
    command = command_line("benchmarks.hard_problems", argv)
    names = args.problems or list(PROBLEMS)
    start = time.perf_counter()
    if not args.report_only:
        configs = configurations(args.full)
        for n in names:
            t = time.perf_counter()
            rows = run_problem(n, PROBLEMS[n], configs, args.out, full=args.full)
            seconds = time.perf_counter() - t
            bad = sum(r.get("status") != "ok" for r in annotate(rows, {}, PROBLEMS))
            write_rows([dict(problem=n, form="full" if args.full else "quick", runs=len(rows),
                             not_ok=bad, seconds=round(seconds, 1), command=command)],
                       os.path.join(args.out, "raw", f"{n}_meta.csv"))
            print(f"{n}: {len(rows)} runs ({bad} not ok) in {seconds:.0f} s", flush=True)
            jax.clear_caches()
    elapsed = None if args.report_only else time.perf_counter() - start
    write_report(args.out, command=command, elapsed=elapsed)
    print(f"report: {os.path.join(args.out, 'report.md')}")


if __name__ == "__main__":
    main()
