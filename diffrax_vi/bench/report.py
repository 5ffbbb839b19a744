"""Tables and figures from the rows of `work_precision`, `long_time_energy` and
`stability_sweep`: markdown tables, PNG plots (matplotlib, imported only here), and the cost of
each solver at a given final error, read off its work-precision curve."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from .stability_results import (
    REFERENCE_RATES,
    accuracy_tolerance,
    convergence_rates,
    stability_target,
)

__all__ = [
    "time_at_error",
    "ratio_table",
    "work_precision_table",
    "energy_table",
    "stability_table",
    "stability_target_table",
    "markdown",
    "plot_work_precision",
    "work_precision_front",
    "plot_energy",
    "plot_convergence_heatmap",
]


def _fmt(x: Any, spec: str = ".2e") -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "–"
    if isinstance(x, float | int) and not isinstance(x, bool):
        return format(x, spec)
    return str(x)


def markdown(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    """A markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


# -- cost at equal error -----------------------------------------------------------------------
def _front(rows: Iterable[dict]) -> list[tuple[float, float]]:
    """(wall, error) of the successful points, cheapest first, keeping only points that are
    more accurate than every cheaper one (the Pareto front of the work-precision curve)."""
    pts = sorted(
        (r["wall_s"], r["error"]) for r in rows
        if r.get("status") == "ok" and r.get("error") is not None and r.get("wall_s")
        and r["error"] > 0
    )
    front: list[tuple[float, float]] = []
    for wall, err in pts:
        if not front or err < front[-1][1]:
            front.append((wall, err))
    return front


def time_at_error(rows: Iterable[dict], target: float) -> tuple[float | None, str]:
    """Wall time needed to reach final error `target`, log-log interpolated on the solver's
    work-precision front. Returns `(time, how)`: `how` is `"interpolated"`, `"at most"` (the
    cheapest point is already more accurate than `target`: its time is an upper bound) or
    `"unreachable"` (no point reaches `target`; time `None`)."""
    front = _front(rows)
    if not front or front[-1][1] > target:
        return None, "unreachable"
    if front[0][1] <= target:
        return front[0][0], "at most"
    for (w0, e0), (w1, e1) in zip(front, front[1:], strict=False):
        if e1 <= target <= e0:
            s = (math.log(target) - math.log(e0)) / (math.log(e1) - math.log(e0))
            return math.exp(math.log(w0) + s * (math.log(w1) - math.log(w0))), "interpolated"
    return None, "unreachable"  # pragma: no cover - the front is monotone


def ratio_table(rows: Sequence[dict], targets: Sequence[float] = (1e-8, 1e-12)) -> list[dict]:
    """Per problem and target error: the best of our solvers (`family == "ours"`), the best
    peer, their times at that error and the ratio ours / peer (< 1: ours is faster)."""
    out = []
    for problem in dict.fromkeys(r["problem"] for r in rows):
        prow = [r for r in rows if r["problem"] == problem]
        for target in targets:
            best: dict[str, tuple] = {}
            for solver in dict.fromkeys(r["solver"] for r in prow):
                srows = [r for r in prow if r["solver"] == solver]
                t, how = time_at_error(srows, target)
                if t is None:
                    continue
                family = srows[0]["family"]
                if family not in best or t < best[family][1]:
                    best[family] = (solver, t, how)
            ours, peer = best.get("ours"), best.get("peer")
            out.append(dict(
                problem=problem, target=target,
                ours=ours[0] if ours else None, ours_s=ours[1] if ours else None,
                ours_how=ours[2] if ours else "unreachable",
                peer=peer[0] if peer else None, peer_s=peer[1] if peer else None,
                peer_how=peer[2] if peer else "unreachable",
                ratio=(ours[1] / peer[1]) if ours and peer else None,
            ))
    return out


# -- tables ------------------------------------------------------------------------------------
def work_precision_table(rows: Sequence[dict]) -> str:
    """All work-precision points as a markdown table."""
    header = ["problem", "solver", "param", "status", "steps", "error", "energy err",
              "wall ms", "compile s", "iterations"]
    body = [
        (r["problem"], r["solver"], f"{r['parameter']}={_fmt(r['value'], 'g')}", r["status"],
         _fmt(r.get("steps"), "d") if isinstance(r.get("steps"), int) else _fmt(r.get("steps")),
         _fmt(r.get("error")), _fmt(r.get("energy_error")),
         _fmt(None if r.get("wall_s") is None else 1e3 * r["wall_s"], ".3g"),
         _fmt(r.get("compile_s"), ".1f"), _fmt(r.get("iterations"), "d"))
        for r in rows
    ]
    return markdown(header, body)


def ratio_markdown(ratios: Sequence[dict]) -> str:
    """`ratio_table` as markdown."""
    def t(s, how):
        if s is None:
            return "unreachable"
        return ("≤ " if how == "at most" else "") + f"{1e3 * s:.3g} ms"

    body = [
        (r["problem"], f"{r['target']:.0e}", r["ours"] or "–", t(r["ours_s"], r["ours_how"]),
         r["peer"] or "–", t(r["peer_s"], r["peer_how"]), _fmt(r["ratio"], ".3g"))
        for r in ratios
    ]
    return markdown(["problem", "final error", "NetworkVI (best)", "time", "best peer", "time",
                     "ratio NetworkVI / peer"], body)


def energy_table(rows: Sequence[dict]) -> str:
    """Per problem and run of `long_time_energy`: cost, steps and the energy error at the end."""
    last: dict[tuple, dict] = {}
    for r in rows:
        last[(r["problem"], r["solver"], r["value"])] = r
    body = [
        (r["problem"], r["solver"], f"{r['parameter']}={_fmt(r['value'], 'g')}",
         _fmt(r.get("horizon"), "g"), r.get("status"), _fmt(r.get("steps"), "d"),
         _fmt(r.get("wall_s"), ".3g"), _fmt(r.get("energy_error")))
        for r in last.values()
    ]
    return markdown(["problem", "solver", "param", "horizon", "status", "steps", "wall s",
                     "max energy error"], body)


ACCEPTANCE_LABELS = {"strict": "ours", "reference": "the reference's"}


def stability_target_table(rows: Sequence[dict]) -> str:
    """The restated target (`stability.stability_target`): the strict rates at `dt ≤ 1`, the
    large-step cases split into accurate / failed / wrong, and each of those cases under
    `RetryFailedSteps` (whether it reaches `t1`, and its error there)."""
    target = stability_target(rows)
    order = {"float64": 0, "float32": 1, "float16": 2}

    def keys(table):
        return sorted(table, key=lambda k: (k[0], order.get(k[1], 3)))

    def counts(table):
        return ("–" if not table else
                f"{table['accurate']} / {table['failed']} / {table['wrong']}")

    body = []
    for key in keys(target["rates"]):
        g = target["rates"][key]
        retry = target["retry"].get(key)
        large = target["large"].get(key, {})
        adaptive = {c: target["adaptive"].get(c, {}).get(key) for c in ("retry", "pid")}
        body.append((
            key[0], key[1], f"{g['converged']}/{g['cases']} ({100 * g['rate']:.0f} %)",
            "–" if g.get("retry_rate") is None else
            f"{round(g['retry_rate'] * g['cases'])}/{g['cases']} "
            f"({100 * g['retry_rate']:.0f} %)",
            str(g.get("wrong", 0)),
            f"{100 * g['target']:.0f} %", "yes" if g["met"] else "**no**",
            f"{large.get('accurate', 0)} / {large.get('failed', 0)} / {large.get('wrong', 0)}"
            if large else "–",
            "–" if retry is None else f"{retry['reached']}/{retry['cases']}",
            "–" if retry is None else _fmt(retry["max_err_t1"]),
            counts(adaptive["retry"]), counts(adaptive["pid"]),
        ))
    text = markdown(["solver", "precision", "converged, dt ≤ 1",
                     "converged, dt ≤ 1, retrying failed steps", "dt ≤ 1: wrong", "target", "met",
                     "dt > 1: accurate / failed / wrong", "retry: reached t1",
                     "retry: largest err_t1", "retry (every dt): accurate / failed / wrong",
                     "pid: accurate / failed / wrong"], body)
    tolerances = ", ".join(f"{d} {accuracy_tolerance(d):.2g}"
                           for d in ("float64", "float32", "float16"))
    pairs = sorted(target["pairs"], key=lambda p: (p["solver"], order.get(p["dtype"], 3),
                                                    p["problem"], p["activation"], p["dt"]))
    per = [
        (p["problem"], _fmt(p["dt"], "g"), p["dtype"], p["activation"], p["solver"],
         p["outcome"] if p["outcome"] != "wrong" else "**wrong**",
         p["result"] or "–", _fmt(p["err_t1"]),
         "–" if p["retry_reached"] is None else ("yes" if p["retry_reached"] else "**no**"),
         _fmt(p["retry_err_t1"]), _fmt(p["retry_steps"], "d"), _fmt(p["retry_rejected"], "d"),
         "–" if p.get("pid_outcome") is None else (
             p["pid_outcome"] if p["pid_outcome"] != "wrong" else "**wrong**"),
         _fmt(p.get("pid_err_t1")), _fmt(p.get("pid_steps"), "d"))
        for p in pairs
    ]
    verdict = "met" if target["met"] else "**not met**"
    if not target["retry"]:
        verdict = "not checked: no runs under `RetryFailedSteps` (`quick_grid` adds them)"
    text += (
        f"\n\nTarget {verdict}. Cases with dt > 1, each "
        "with constant steps, again under `RetryFailedSteps` and under `PIDController` with "
        "the error estimate at rtol = atol = sqrt(eps) (accurate: successful with "
        f"`err_t1` at most {tolerances}; `err_t1` = max|q(t1) − q_ref(t1)| over the largest "
        "|q_ref| of the run):\n\n"
    )
    text += markdown(["problem", "dt", "precision", "activation", "solver", "outcome",
                      "result", "err_t1", "retry: reached t1", "retry: err_t1",
                      "retry: steps", "retry: rejected", "pid: outcome", "pid: err_t1",
                      "pid: steps"], per)
    return text


def stability_table(rows: Sequence[dict]) -> str:
    """The restated target (`stability_target_table`, where the rows have a `result`), then
    convergence per precision and convergence test next to the reference's quick run, then
    (our test) status counts per problem and solver and the best configuration per problem.
    Only the constant-step cases count outside the target's table."""
    prefix = ""
    if any("result" in r and r.get("result") is not None for r in rows):
        prefix = ("Restated target (issue 52), our convergence test:\n\n"
                  + stability_target_table(rows)
                  + "\n\nConvergence of every case next to the reference's quick run:\n\n")
    rows = [r for r in rows if (r.get("controller") or "constant") == "constant"]
    body = []
    for acceptance in ("strict", "reference"):
        subset = [r for r in rows if (r.get("acceptance") or "strict") == acceptance]
        rates = convergence_rates(subset, "dtype")
        for dtype in ("float16", "float32", "float64"):
            if dtype not in rates:
                continue
            r = rates[dtype]
            ref = REFERENCE_RATES[dtype]
            body.append((dtype, ACCEPTANCE_LABELS[acceptance], r["cases"], r["converged"],
                         f"{100 * r['rate']:.0f} %",
                         f"{100 * ref[0] / ref[1]:.0f} % ({ref[0]}/{ref[1]})", r["measured"],
                         _fmt(r["ref_err"]), _fmt(r["ham_drift"]), _fmt(r["iterations"], "g")))
    text = markdown(["precision", "convergence test", "cases", "converged", "rate",
                     "reference rate", "measured", "median ref_err", "median ham_drift",
                     "median iter"], body)
    rows = [r for r in rows if (r.get("acceptance") or "strict") == "strict"]
    statuses = sorted({r["status"] for r in rows})
    per = []
    for problem in dict.fromkeys(r["problem"] for r in rows):
        for solver in dict.fromkeys(r["solver"] for r in rows):
            rs = [r for r in rows if r["problem"] == problem and r["solver"] == solver]
            if rs:
                per.append((problem, solver, *(sum(r["status"] == s for r in rs)
                                               for s in statuses)))
    text += "\n\nStatus counts per problem and nonlinear solver (our convergence test):\n\n"
    text += markdown(["problem", "solver", *statuses], per)
    best = []
    for problem in dict.fromkeys(r["problem"] for r in rows):
        rs = [r for r in rows if r["problem"] == problem and r["status"] in ("ok", "maxiter")
              and r.get("ref_err") is not None]
        if rs:
            b = min(rs, key=lambda r: r["ref_err"])
            best.append((problem, _fmt(b["ref_err"]), b["dtype"], _fmt(b["dt"], "g"),
                         f"R{b['nodes']} S{b['width']} {b['activation']}", b["solver"],
                         b["status"]))
    text += "\n\nBest configuration per problem (lowest ref_err over measured cases):\n\n"
    text += markdown(["problem", "ref_err", "precision", "dt", "network", "solver", "status"],
                     best)
    return prefix + text


# -- plots -------------------------------------------------------------------------------------
def pyplot():
    """matplotlib's `pyplot` on the file-only Agg backend (imported on first use)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def subplot_grid(n: int):
    """`(rows, columns)` of a grid of `n` panels, at most three to a row."""
    cols = min(n, 3)
    rows = math.ceil(n / cols)
    return rows, cols


def work_precision_front(rows: Iterable[dict]) -> list[tuple[float, float]]:
    """`(error, wall)` of one solver's front, ordered by error (most accurate first): the
    successful points that no other point beats in both error and time. Along it the error
    grows and the time falls, so the curve drawn through it never turns back."""
    return sorted((err, wall) for wall, err in _front(rows))


_STYLE = {"ours": dict(marker="o", ls="-", lw=2, ms=6),
          "peer": dict(marker="s", ls="--", lw=1, ms=4)}


def plot_work_precision(rows: Sequence[dict], path) -> None:
    """Wall time against final error, one panel per problem. Each solver's front
    (`work_precision_front`) is a curve ordered by error; its other points, slower than a
    more accurate one, are drawn as faint markers of the same colour, unjoined."""
    plt = pyplot()
    problems = list(dict.fromkeys(r["problem"] for r in rows))
    nr, nc = subplot_grid(len(problems))
    fig, axes = plt.subplots(nr, nc, figsize=(5 * nc, 4 * nr), squeeze=False)
    for ax, problem in zip(axes.flat, problems, strict=False):
        for solver in dict.fromkeys(r["solver"] for r in rows if r["problem"] == problem):
            srows = [r for r in rows if r["problem"] == problem and r["solver"] == solver]
            front = work_precision_front(srows)
            if not front:
                continue
            style = _STYLE.get(srows[0]["family"], _STYLE["peer"])
            (line,) = ax.loglog(*zip(*front, strict=True), label=solver, **style)
            on_front = set(front)
            rest = [(r["error"], r["wall_s"]) for r in srows
                    if r.get("status") == "ok" and r.get("error") and r.get("wall_s")
                    and (r["error"], r["wall_s"]) not in on_front]
            if rest:
                ax.loglog(*zip(*rest, strict=True), ls="none", marker=style["marker"],
                          ms=style["ms"], color=line.get_color(), alpha=0.35)
        ax.set_title(problem)
        ax.set_xlabel("final error (relative, q)")
        ax.set_ylabel("wall time after compilation [s]")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    save_grid(plt, fig, axes, len(problems), path)


def save_grid(plt, fig, axes, used: int, path) -> None:
    """Blank the panels of a figure grid past the first `used`, then save and close it."""
    for ax in axes.flat[used:]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_energy(rows: Sequence[dict], path) -> None:
    """Running maximum of the relative energy error against time, per problem."""
    plt = pyplot()
    problems = list(dict.fromkeys(r["problem"] for r in rows))
    nr, nc = subplot_grid(len(problems))
    fig, axes = plt.subplots(nr, nc, figsize=(5 * nc, 4 * nr), squeeze=False)
    for ax, problem in zip(axes.flat, problems, strict=False):
        runs = dict.fromkeys((r["solver"], r["value"]) for r in rows if r["problem"] == problem)
        for solver, value in runs:
            pts = [(r["t"], r["energy_error"]) for r in rows
                   if r["problem"] == problem and r["solver"] == solver and r["value"] == value
                   and r.get("t") is not None and r.get("energy_error")]
            if not pts:
                continue
            wall = next(r.get("wall_s") for r in rows if r["problem"] == problem
                        and r["solver"] == solver and r["value"] == value)
            label = f"{solver} ({_fmt(value, 'g')}; {_fmt(wall, '.3g')} s)"
            ax.loglog(*zip(*pts, strict=True), label=label)
        ax.set_title(problem)
        ax.set_xlabel("t")
        ax.set_ylabel("max |H − H₀| / |H₀| so far")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    save_grid(plt, fig, axes, len(problems), path)


def plot_convergence_heatmap(rows: Sequence[dict], path) -> None:
    """Convergence rate (ok / cases) per nonlinear solver × precision, one panel per problem
    and one for all problems together."""
    plt = pyplot()
    rows = [r for r in rows if (r.get("acceptance") or "strict") == "strict"
            and (r.get("controller") or "constant") == "constant"]
    problems = list(dict.fromkeys(r["problem"] for r in rows))
    solvers = list(dict.fromkeys(r["solver"] for r in rows))
    dtypes = [d for d in ("float16", "float32", "float64") if any(r["dtype"] == d for r in rows)]
    panels = [*problems, "all problems"]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 2.2 + 0.4 * len(solvers)),
                             squeeze=False)
    for ax, panel in zip(axes.flat, panels, strict=True):
        rs = rows if panel == "all problems" else [r for r in rows if r["problem"] == panel]
        grid = np.full((len(solvers), len(dtypes)), np.nan)
        for i, s in enumerate(solvers):
            for j, d in enumerate(dtypes):
                sel = [r for r in rs if r["solver"] == s and r["dtype"] == d]
                if sel:
                    grid[i, j] = sum(r["status"] == "ok" for r in sel) / len(sel)
        ax.imshow(grid, vmin=0, vmax=1, cmap="viridis", aspect="auto")
        for i in range(len(solvers)):
            for j in range(len(dtypes)):
                if not np.isnan(grid[i, j]):
                    ax.text(j, i, f"{100 * grid[i, j]:.0f}%", ha="center", va="center",
                            color="w" if grid[i, j] < 0.6 else "k")
        ax.set_xticks(range(len(dtypes)), dtypes)
        ax.set_yticks(range(len(solvers)), solvers if ax is axes.flat[0] else [""] * len(solvers))
        ax.set_title(panel, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def equal_cost(rows: Sequence[dict], peers: Sequence[str] = ("Tsit5", "Dopri8")) -> list[dict]:
    """Per problem of `long_time_energy`: the NetworkVI run and, for each peer, the run whose
    wall time is closest (in ratio) to NetworkVI's, with their final energy errors."""
    last: dict[tuple, dict] = {}
    for r in rows:
        last[(r["problem"], r["solver"], r["value"])] = r
    out = []
    for problem in dict.fromkeys(r["problem"] for r in rows):
        runs = [r for (p, _, _), r in last.items() if p == problem]
        ours = [r for r in runs if r.get("family") == "ours" and r.get("wall_s")]
        for o in ours:
            entry = dict(problem=problem, ours=o["solver"], steps=o.get("steps"),
                         horizon=o.get("horizon"), ours_s=o["wall_s"], ours_status=o["status"],
                         ours_energy=o.get("energy_error"))
            for peer in peers:
                cands = [r for r in runs if r["solver"] == peer and r.get("status") == "ok"
                         and r.get("wall_s")]
                if not cands:
                    entry[peer] = None
                    continue
                best = min(cands, key=lambda r: abs(math.log(r["wall_s"] / o["wall_s"])))
                entry[peer] = dict(rtol=best["value"], wall_s=best["wall_s"],
                                   energy=best.get("energy_error"), steps=best.get("steps"))
            out.append(entry)
    return out


def equal_cost_markdown(rows: Sequence[dict], peers: Sequence[str] = ("Tsit5", "Dopri8")) -> str:
    """`equal_cost` as markdown."""
    body = []
    for e in equal_cost(rows, peers):
        cells = [e["problem"],
                 f"{e['ours']}: {_fmt(e['steps'], 'd')} steps, T = {_fmt(e['horizon'], 'g')}",
                 f"{_fmt(e['ours_s'], '.3g')} s", f"{_fmt(e['ours_energy'])} ({e['ours_status']})"]
        for p in peers:
            c = e.get(p)
            cells.append("–" if c is None else
                         f"{_fmt(c['energy'])} (rtol {c['rtol']:.0e}, {c['wall_s']:.3g} s)")
        body.append(cells)
    return "Energy error at the end, NetworkVI against each peer's run of the closest cost:\n\n" + \
        markdown(["problem", "NetworkVI run", "NetworkVI time", "NetworkVI energy error",
                  *(f"{p} (closest cost)" for p in peers)], body)
