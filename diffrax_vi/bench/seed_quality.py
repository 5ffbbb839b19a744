"""Seed-quality study of the OGA on its own (no integrator).

Every dictionary × selection × fit, for every activation and precision, fits the four target
functions of the reference's study (width 4, 11 Simpson nodes on `[0, 1]`, dictionaries of
about 800 atoms, biases in `[-π, π]`). Each case is scored in float64 from the parameters the
fit returned (rounded to its working dtype):

- `finite`: all of `W`, `b`, `c` and the reported residual are finite;
- `fit_err`: the weighted L² error `sqrt(Σ w_j (u(t_j) − y_j)²)` of the returned network;
- `sigma_min`, `cond`: extreme singular values of the weighted seed design
  `sqrt(w_j) σ(W_k t_j + b_k)` (all `width` neurons, placeholders included);
- `rank`: its numerical rank at the working precision (singular values above
  `σ_max · eps(T)`); in float16 placeholder neurons of a seed that placed fewer than
  `width` neurons often make it short. A *singular* seed (non-finite, or `σ_min = 0`:
  duplicated neurons) makes the integrator's Jacobian singular from the first iteration;
- `neurons`, `rejected`: neurons placed by the greedy loop and atoms refused as dependent.

One compilation serves all activations and targets of a configuration and dtype (the
activation is chosen by a traced index), which keeps the 6048-case grid to 216 compilations.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import statistics
import time
from collections.abc import Callable, Iterable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..activations import check_activation, elu, gelu, relu_k, tanh
from ..ansatz.symmetry import NoSymmetry
from ..oga import (
    OGA,
    AngularGrid,
    BiasGrid1d,
    IncrementalQR,
    NormalEquationsFit,
    NormalizedProjection,
    OGA1d,
    OGA1dNormalEquations,
    OGA1dNormalized,
    OGA1dStable,
    OGA2d,
    OGAReference,
    OGASphere,
    OrthogonalProjection,
    PivotedQR,
    RawProjection,
    Refined,
    TruncatedSVD,
    WeightBiasGrid2d,
    WeightedQR,
    oga_fit,
)
from ..oga.greedy import oga_fit_traced
from ..oga.reference import oga_reference_fit
from ..quadrature import Simpson

__all__ = [
    "TARGETS",
    "ACTIVATIONS",
    "DICTIONARIES",
    "SELECTIONS",
    "FITS",
    "PRESETS",
    "SeedCase",
    "study_configs",
    "run_study",
    "run_case",
    "write_csv",
    "summary_markdown",
    "time_large_dictionary",
]

TARGETS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "smooth": lambda t: np.cos(3 * t),
    "oscillatory": lambda t: np.cos(12 * t),
    "exponential": lambda t: np.exp(2 * t) / 4,
    "twofreq": lambda t: 0.4 * np.cos(7 * t) + 0.3 * np.sin(11 * t + 1),
}
ACTIVATIONS: dict[str, Callable] = {
    "relu1": relu_k(1),
    "relu2": relu_k(2),
    "relu3": relu_k(3),
    "relu4": relu_k(4),
    "elu": elu,
    "gelu": gelu,
    "tanh": tanh,
}
# Sizes held near 800 atoms, as in the reference's study.
DICTIONARIES = {
    "grid1d": BiasGrid1d(),
    "grid2d": WeightBiasGrid2d(octaves=(-3.0, 3.0), weight_amount=6, bias_amount=56),
    "angular": AngularGrid(radii=(0.25, 1.0, 4.0), amount=266),
    "refined": Refined(BiasGrid1d(), iterations=4),
}
SELECTIONS = {
    "raw": RawProjection(),
    "normalized": NormalizedProjection(),
    "orthogonal": OrthogonalProjection(),
}
FITS = {
    "qr": WeightedQR(),
    "incqr": IncrementalQR(),
    "pivqr": PivotedQR(),
    "tsvd": TruncatedSVD(),
    "normaleq": NormalEquationsFit(ridge=True),
    "normaleq+f64": NormalEquationsFit(ridge=False, island=True),
}
PRESETS: dict[str, Callable[[], OGA | OGAReference]] = {
    "OGA1d": OGA1d,
    "OGA1dNormalized": OGA1dNormalized,
    "OGA1dStable": OGA1dStable,
    "OGA2d": OGA2d,
    "OGASphere": OGASphere,
    "OGA1dNormalEquations": OGA1dNormalEquations,
}
PRECISIONS = ("float16", "float32", "float64")
WIDTH = 4
NUM_INTERVALS = 10
DICT_AMOUNT = 400
BIAS_INTERVAL = (-math.pi, math.pi)


@dataclasses.dataclass(frozen=True)
class SeedCase:
    """One fitted seed and its scores (see the module docstring)."""

    group: str  # "grid" (dictionary × selection × fit) or "preset"
    config: str
    dictionary: str
    selection: str
    fit: str
    precision: str
    activation: str
    target: str
    finite: bool
    fit_err: float
    sigma_min: float
    cond: float
    rank: int
    neurons: int
    rejected: int


class _IndexedActivation(eqx.Module):
    """`ACTIVATIONS[index]`, with a (possibly traced) index: one compilation for all of them."""

    index: Array

    def __call__(self, x):
        branches = [lambda v, f=f: f(v) for f in ACTIVATIONS.values()]
        return jax.lax.switch(self.index, branches, x)


@eqx.filter_jit
def _fit_batch(config, nodes, weights, ys, indices):
    def one(y, index):
        activation = _IndexedActivation(index)
        if config.reference:
            return oga_reference_fit(
                activation, nodes, weights, y, WIDTH, BIAS_INTERVAL, DICT_AMOUNT
            )
        return oga_fit_traced(
            config, activation, nodes, weights, y, WIDTH, BIAS_INTERVAL, DICT_AMOUNT, None,
            NoSymmetry(),
        )  # fmt: skip

    return jax.vmap(one)(ys, indices)


def study_configs() -> list[tuple[str, str, str, str, OGA]]:
    """`(label, dictionary, selection, fit, config)` for the whole grid (72 configurations)."""
    configs = []
    for dname, dictionary in DICTIONARIES.items():
        for sname, selection in SELECTIONS.items():
            for fname, fit in FITS.items():
                config = OGA(dictionary, selection, fit)
                configs.append((f"{dname}/{sname}/{fname}", dname, sname, fname, config))
    return configs


def _score(params, activation, nodes64, weights64, y64, dtype) -> dict:
    w, b, c, residual = (np.asarray(v, np.float64) for v in params)
    finite = bool(np.all(np.isfinite(w)) and np.all(np.isfinite(b)) and np.all(np.isfinite(c))
                  and np.isfinite(residual))  # fmt: skip
    if not finite:
        return dict(finite=False, fit_err=math.inf, sigma_min=0.0, cond=math.inf, rank=0)
    design = np.asarray(activation(jnp.asarray(np.outer(nodes64, w) + b, jnp.float64)))
    sqrt_w = np.sqrt(weights64)
    fit_err = float(np.linalg.norm(sqrt_w * (design @ c - y64)))
    sv = np.linalg.svd(sqrt_w[:, None] * design, compute_uv=False)
    tol = sv[0] * float(np.finfo(dtype).eps)
    return dict(
        finite=True,
        fit_err=fit_err,
        sigma_min=float(sv[-1]),
        cond=float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf,
        rank=int(np.sum(sv > tol)),
    )


def _run_config(group, label, dname, sname, fname, config, precision) -> list[SeedCase]:
    dtype = np.dtype(precision)
    t64, w64 = Simpson(NUM_INTERVALS).nodes_weights_np()
    nodes, weights = jnp.asarray(t64, dtype), jnp.asarray(w64, dtype)
    pairs = [(a, t) for a in ACTIVATIONS for t in TARGETS]
    ys64 = np.stack([TARGETS[t](t64) for _, t in pairs])
    indices = jnp.asarray([list(ACTIVATIONS).index(a) for a, _ in pairs], jnp.int32)
    res = _fit_batch(config, nodes, weights, jnp.asarray(ys64, dtype), indices)
    cases = []
    for k, (aname, tname) in enumerate(pairs):
        params = (res.W[k], res.b[k], res.c[k], res.residual[k])
        scores = _score(params, ACTIVATIONS[aname], t64, w64, ys64[k], dtype)
        cases.append(
            SeedCase(
                group=group, config=label, dictionary=dname, selection=sname, fit=fname,
                precision=precision, activation=aname, target=tname, neurons=int(res.placed[k]),
                rejected=int(res.rejected[k]), **scores,
            )  # fmt: skip
        )
    return cases


def run_case(group: str, config: str, precision: str) -> list[SeedCase]:
    """Fit and score one configuration in one precision (every activation and target): a
    label of `study_configs()` when `group` is `"grid"`, a key of `PRESETS` when it is
    `"preset"`. The unit of work of the study on a cluster (`sweeps.SeedQualitySweep`)."""
    if group == "grid":
        found = [c for c in study_configs() if c[0] == config]
        if not found:
            raise ValueError(f"no grid configuration {config!r}; see study_configs()")
        label, dname, sname, fname, oga = found[0]
    elif group == "preset":
        if config not in PRESETS:
            raise ValueError(f"no preset {config!r}; choose from {sorted(PRESETS)}")
        oga = PRESETS[config]()
        label, dname, sname, fname = config, "", "", oga.label
    else:
        raise ValueError(f"group must be 'grid' or 'preset', got {group!r}")
    return _run_config(group, label, dname, sname, fname, oga, precision)


def run_study(
    precisions: Sequence[str] = PRECISIONS,
    configs: Iterable[tuple[str, str, str, str, OGA]] | None = None,
    presets: bool = True,
    progress: Callable[[str], None] | None = None,
) -> list[SeedCase]:
    """Fit and score every case; `configs` defaults to the whole grid (`study_configs()`).

    With `presets`, the named presets (their own default dictionaries, `dict_amount` 400)
    are scored as well, including the reference baseline `OGA1dNormalEquations`, which
    needs `jax_enable_x64`.
    """
    for precision in precisions:
        for activation in ACTIVATIONS.values():
            check_activation(activation, np.dtype(precision))
    jobs = [("grid",) + c for c in (study_configs() if configs is None else configs)]
    if presets:
        for name, make in PRESETS.items():
            config = make()
            jobs.append(("preset", name, "", "", config.label, config))
    cases = []
    for n, (group, label, dname, sname, fname, config) in enumerate(jobs):
        for precision in precisions:
            start = time.perf_counter()
            cases += _run_config(group, label, dname, sname, fname, config, precision)
            jax.clear_caches()  # hundreds of compilations: keep the memory bounded
            if progress is not None:
                progress(
                    f"[{n + 1}/{len(jobs)}] {label} {precision}: "
                    f"{time.perf_counter() - start:.1f} s"
                )
    return cases


def write_csv(cases: Sequence[SeedCase], path) -> None:
    """One row per case, columns as the fields of `SeedCase`."""
    fields = [f.name for f in dataclasses.fields(SeedCase)]
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields)
        writer.writeheader()
        for case in cases:
            writer.writerow(dataclasses.asdict(case))


def _median(values) -> float:
    values = [v for v in values if math.isfinite(v)]
    return statistics.median(values) if values else math.nan


def summary_markdown(cases: Sequence[SeedCase]) -> str:
    """Markdown tables: failures and rank per (precision, selection); fit error per
    (precision, fit); the presets, with the rank loss of the reference baseline."""
    grid = [c for c in cases if c.group == "grid"]
    precisions = [p for p in PRECISIONS if any(c.precision == p for c in cases)]
    out = []
    if grid:
        out += [
            f"### Grid: {len(grid)} cases, {sum(not c.finite for c in grid)} non-finite", "",
            "| precision | selection | cases | non-finite | short of full width "
            "| with rejections | most rejected | rank-deficient seeds |",
            "|---|---|---|---|---|---|---|---|",
        ]  # fmt: skip
        for p in precisions:
            for s in SELECTIONS:
                cs = [c for c in grid if c.precision == p and c.selection == s]
                if not cs:
                    continue
                out.append(
                    f"| {p} | {s} | {len(cs)} | {sum(not c.finite for c in cs)} "
                    f"| {sum(c.neurons < WIDTH for c in cs)} | {sum(c.rejected > 0 for c in cs)} "
                    f"| {max(c.rejected for c in cs)} | {sum(c.rank < WIDTH for c in cs)} |"
                )
        out += ["", "Median fit error (all dictionaries, selections, activations, targets):", ""]
        fits = [f for f in FITS if any(c.fit == f for c in grid)]
        out += ["| precision | " + " | ".join(fits) + " |", "|---|" + "---|" * len(fits)]
        for p in precisions:
            row = [_median(c.fit_err for c in grid if c.precision == p and c.fit == f)
                   for f in fits]  # fmt: skip
            out.append(f"| {p} | " + " | ".join(f"{v:.2e}" for v in row) + " |")
        out += ["", "Best configuration per (precision, activation), by median fit error:", ""]
        out += ["| precision | activation | best | median fit error |", "|---|---|---|---|"]
        for p in precisions:
            for a in ACTIVATIONS:
                by_config: dict[str, list[float]] = {}
                for c in grid:
                    if c.precision == p and c.activation == a:
                        by_config.setdefault(c.config, []).append(c.fit_err)
                if by_config:
                    best = min(by_config, key=lambda k: _median(by_config[k]))
                    out.append(f"| {p} | {a} | {best} | {_median(by_config[best]):.2e} |")
    presets = [c for c in cases if c.group == "preset"]
    if presets:
        out += [
            "", "### Presets (their default dictionaries, dict_amount 400)", "",
            "| preset | precision | non-finite | singular seeds | rank-deficient seeds "
            "| median fit error | median σ_min |",
            "|---|---|---|---|---|---|---|",
        ]  # fmt: skip
        for name in PRESETS:
            for p in precisions:
                cs = [c for c in presets if c.config == name and c.precision == p]
                if cs:
                    out.append(
                        f"| {name} | {p} | {sum(not c.finite for c in cs)}/{len(cs)} "
                        f"| {sum(not c.finite or c.sigma_min == 0 for c in cs)}/{len(cs)} "
                        f"| {sum(c.rank < WIDTH for c in cs)}/{len(cs)} "
                        f"| {_median(c.fit_err for c in cs):.2e} "
                        f"| {_median(c.sigma_min for c in cs):.2e} |"
                    )
    return "\n".join(out) + "\n"


def time_large_dictionary(
    dict_amount: int = 50000, width: int = 10, repeats: int = 30, batch: int = 8,
    dtype=np.float64,
) -> dict[str, float]:  # fmt: skip
    """Median wall time (ms) of one jitted `OGA1d` tanh fit on 11 Simpson nodes, after
    compilation; and of `batch` targets under one `vmap`, against a Python loop of single fits."""
    t64, w64 = Simpson(NUM_INTERVALS).nodes_weights_np()
    # NumPy nodes and weights are compile-time constants: the dictionary is built once, as in
    # NetworkVI (jax arrays closed over by jit are traced, and the dictionary rebuilt per call).
    nodes, weights = t64.astype(dtype), w64.astype(dtype)
    ys = jnp.asarray(np.stack([np.cos((1 + 0.5 * k) * t64) for k in range(batch)]), dtype)
    config = OGA1d()

    def fit(y):
        return oga_fit(config, tanh, nodes, weights, y, width, dict_amount=dict_amount)

    single = jax.jit(fit)
    batched = jax.jit(jax.vmap(fit))
    start = time.perf_counter()
    jax.block_until_ready(single(ys[0]))
    compile_s = time.perf_counter() - start
    jax.block_until_ready(batched(ys))

    def median_ms(call):
        samples = []
        for _ in range(repeats):
            start = time.perf_counter()
            jax.block_until_ready(call())
            samples.append(time.perf_counter() - start)
        return 1e3 * statistics.median(samples)

    return dict(
        atoms=2 * (dict_amount + 1),
        compile_s=compile_s,
        single_ms=median_ms(lambda: single(ys[0])),
        vmap_ms=median_ms(lambda: batched(ys)),
        loop_ms=median_ms(lambda: [single(y) for y in ys]),
        batch=batch,
    )
