"""Structure preservation, shown by measurement: symplecticity of the one-step map, time
symmetry, bounded energy over long runs, discrete Noether invariants, and precision.

Run with `-s` to see the measured figures (they are printed as `FIGURE ...` lines).
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffrax_vi as dvi
from diffrax_vi import problems


def figure(name, value):
    print(f"FIGURE {name}: {value:.3e}")


def shallow(width=10, nodes=8, **kwargs):
    return dvi.ShallowNet(dvi.ShallowNetBasis(dvi.tanh, width), dvi.GaussLegendre(nodes), **kwargs)


# -- symplecticity --------------------------------------------------------------------------


def one_step_jacobian(solver, problem, h):
    """`M = ∂(q_{n+1}, p_{n+1}) / ∂(q_n, p_n)` of one step from `problem.y0`, by forward-mode
    differentiation through the converged solve (implicit function theorem)."""
    d = problem.dim
    term, args = problem.term, problem.args
    z0 = jnp.concatenate(problem.y0)
    t0 = jnp.asarray(problem.t0, z0.dtype)
    t1 = t0 + jnp.asarray(h, z0.dtype)

    def flow(z):
        y = (z[:d], z[d:])
        state = solver.init(term, t0, t1, y, args)
        (q1, p1), _, _, _, result = solver.step(term, t0, t1, y, args, state, False)
        return jnp.concatenate([q1, p1]), result == diffrax.RESULTS.successful

    m, ok = eqx.filter_jit(jax.jacfwd(flow, has_aux=True))(z0)
    assert bool(ok)
    return np.asarray(m)


def symplectic_defect(m):
    d = m.shape[0] // 2
    j = np.block([[np.zeros((d, d)), np.eye(d)], [-np.eye(d), np.zeros((d, d))]])
    return float(np.max(np.abs(m.T @ j @ m - j)))


def test_symplectic_harmonic_oscillator():
    problem = problems.harmonic_oscillator()
    m = one_step_jacobian(shallow(), problem, problem.dt)
    defect = symplectic_defect(m)
    figure("symplectic defect, harmonic oscillator, ShallowNet tanh S=10 GL8 h=0.1", defect)
    assert defect <= 1e-10
    # Not trivially the identity: the exact flow's Jacobian is a rotation by ωh.
    assert np.max(np.abs(m - np.eye(2))) > 1e-2


@pytest.mark.long
@pytest.mark.parametrize("name", ["double_pendulum", "henon_heiles"])
def test_symplectic_two_degrees_of_freedom(name):
    problem = getattr(problems, name)()
    m = one_step_jacobian(shallow(), problem, problem.dt)
    defect = symplectic_defect(m)
    figure(f"symplectic defect, {name}, ShallowNet tanh S=10 GL8 h={problem.dt}", defect)
    assert defect <= 1e-10


@pytest.mark.long
def test_symplectic_defect_follows_the_nonlinear_tolerance():
    """A step solved to a looser residual is a less exact symplectic map: the defect follows
    the tolerance (printed for the issue note)."""
    problem = problems.harmonic_oscillator()
    defects = {}
    for ftol in (1e-6, 1e-9, 1e-12, None):
        # floor = ftol as well, so that the looser solves are not accepted below it anyway
        finder = dvi.LevenbergMarquardt(ftol=ftol, floor=ftol)
        m = one_step_jacobian(shallow(root_finder=finder), problem, problem.dt)
        defects[ftol] = symplectic_defect(m)
        figure(f"symplectic defect, harmonic oscillator, ftol={ftol}", defects[ftol])
    assert defects[None] <= 1e-10
    assert defects[1e-6] >= defects[None]


# -- time symmetry --------------------------------------------------------------------------


def there_and_back(solver, problem, n, energy=False):
    """Max-norm distance to `y0` after `n` steps forward and `n` steps back (and, with
    `energy`, the max relative energy error over the forward steps)."""
    dtype = problem.y0[0].dtype
    h = jnp.asarray(problem.dt, dtype)
    run = eqx.filter_jit(
        lambda y0, t0, t1, dt: diffrax.diffeqsolve(
            problem.term, solver, t0, t1, dt, y0, args=problem.args, max_steps=128,
            saveat=diffrax.SaveAt(steps=True),
        )
    )  # fmt: skip
    t0 = jnp.asarray(problem.t0, dtype)
    t1 = t0 + n * h
    fwd = run(problem.y0, t0, t1, h)
    q, p = (np.asarray(a[:n]) for a in fwd.ys)
    back = run((fwd.ys[0][n - 1], fwd.ys[1][n - 1]), t1, t0, -h)
    y0 = np.concatenate([np.asarray(a) for a in problem.y0])
    yb = np.concatenate([np.asarray(back.ys[0][n - 1]), np.asarray(back.ys[1][n - 1])])
    distance = float(np.max(np.abs(yb - y0)))
    if not energy:
        return distance
    e = np.asarray(jax.vmap(problem.energy)(fwd.ts[:n], q, p))
    e0 = float(problem.energy(t0, *problem.y0))
    return distance, float(np.max(np.abs(e - e0)) / abs(e0))


@pytest.mark.long  # ~45 s under load; one-step reversibility is also in tests/test_methods.py
def test_time_symmetry_reversible_harmonic_oscillator():
    """Also the short version of the energy study: 100 steps of h = 0.1 with bounded energy."""
    problem = problems.harmonic_oscillator(t1=10.0)
    solver = dvi.ShallowNetReversible(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8))
    one = there_and_back(solver, problem, 1)
    many, energy = there_and_back(solver, problem, 100, energy=True)
    figure("reversibility, ShallowNetReversible, harmonic oscillator, 1 step", one)
    figure("reversibility, ShallowNetReversible, harmonic oscillator, 100 steps", many)
    figure("max rel energy error, ShallowNetReversible, harmonic oscillator, 100 steps", energy)
    assert one <= 1e-13
    assert many <= 1e-11
    assert energy <= 2e-11  # measured 5.1e-12 (the round-off drift of the long runs)


@pytest.mark.long
def test_time_symmetry_reversible_henon_heiles():
    problem = problems.henon_heiles()
    for name, method in [
        ("ShallowNetReversible", dvi.ShallowNetReversible),
        ("ShallowNetAutodiffReversible", dvi.ShallowNetAutodiffReversible),
    ]:
        solver = method(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8))
        one = there_and_back(solver, problem, 1)
        many = there_and_back(solver, problem, 100)
        figure(f"reversibility, {name}, Henon-Heiles, 1 step", one)
        figure(f"reversibility, {name}, Henon-Heiles, 100 steps", many)
        assert one <= 1e-12
        assert many <= 1e-10


# -- long-time energy -----------------------------------------------------------------------


def energy_run(problem, solver, n_steps, n_save=1001):
    t1 = problem.t0 + n_steps * problem.dt
    ts = jnp.linspace(problem.t0, t1, n_save)
    sol = diffrax.diffeqsolve(
        problem.term, solver, problem.t0, t1, problem.dt, problem.y0, args=problem.args,
        saveat=diffrax.SaveAt(ts=ts), max_steps=n_steps + 16,
    )  # fmt: skip
    energy = jax.vmap(problem.energy)(sol.ts, sol.ys[0], sol.ys[1])
    e0 = float(energy[0])
    rel = np.abs(np.asarray(energy) - e0) / abs(e0)
    # Secular growth: the least-squares slope of the relative error, times the run length.
    ts_np = np.asarray(sol.ts)
    slope = np.polyfit(ts_np - ts_np[0], np.asarray(energy) / e0 - 1, 1)[0]
    return float(np.max(rel)), float(abs(slope) * (ts_np[-1] - ts_np[0]))


def check_energy(problem, n_steps, label, vi_bound, trend_per_step):
    vi_max, vi_trend = energy_run(problem, shallow(), n_steps)
    rk_max, rk_trend = energy_run(problem, diffrax.Tsit5(), n_steps)
    figure(f"max rel energy error, ShallowNet, {label}, {n_steps} steps", vi_max)
    figure(f"fitted energy trend over the run, ShallowNet, {label}", vi_trend)
    figure(f"max rel energy error, Tsit5 same h, {label}, {n_steps} steps", rk_max)
    figure(f"fitted energy trend over the run, Tsit5 same h, {label}", rk_trend)
    assert vi_max <= vi_bound
    # Measured: the network's energy error is not a pure oscillation; it grows linearly at
    # the round-off level (about 5e-13 per step for the oscillator at h = 0.5, the same with
    # a 100x stricter acceptance floor: it comes from where the converged solves stop, at
    # ~64 eps). The bound pins that rate; Tsit5 at the same step (which costs it fewer
    # evaluations) drifts about 1e5 times faster, all of it trend.
    assert vi_trend <= trend_per_step * n_steps
    # Tsit5 may leave the bounded region altogether (Hénon–Heiles at h = 0.5, 10⁵ steps: its
    # energy error turns NaN; measured), which is drift in its extreme form.
    if np.isfinite(rk_max):
        assert rk_trend >= 0.5 * rk_max and rk_max >= 1e3 * vi_max


@pytest.mark.long
def test_energy_harmonic_oscillator_short():
    check_energy(problems.harmonic_oscillator(dt=0.5), 2000, "harmonic oscillator h=0.5", 5e-9,
                 2e-12)  # fmt: skip


@pytest.mark.long
def test_energy_harmonic_oscillator_1e5_steps():
    check_energy(problems.harmonic_oscillator(dt=0.5), 100_000, "harmonic oscillator h=0.5",
                 2e-7, 2e-12)  # fmt: skip


@pytest.mark.long
def test_energy_henon_heiles_1e5_steps():
    check_energy(problems.henon_heiles(dt=0.5), 100_000, "Henon-Heiles h=0.5", 1e-5, 1e-10)


FORMULATIONS = [("ShallowNet", dvi.ShallowNet), ("ShallowNetAutodiff", dvi.ShallowNetAutodiff)]


# -- discrete Noether -----------------------------------------------------------------------


def invariant_drift(problem, solver, name, n_steps):
    t1 = problem.t0 + n_steps * problem.dt
    ts = jnp.linspace(problem.t0, t1, 101)
    sol = diffrax.diffeqsolve(
        problem.term, solver, problem.t0, t1, problem.dt, problem.y0, args=problem.args,
        saveat=diffrax.SaveAt(ts=ts), max_steps=n_steps + 16,
    )  # fmt: skip
    invariant = problem.invariants[name]
    values = np.asarray(
        jax.vmap(lambda t, q, p: invariant(t, q, p, problem.args))(sol.ts, sol.ys[0], sol.ys[1])
    )
    return float(np.max(np.abs(values - values[0])) / max(1.0, abs(float(values[0]))))


@pytest.mark.long
def test_noether_toda_total_momentum():
    """The total momentum is the Noether invariant of translations `q ↦ q + c(1, .., 1)`.
    Interpolating endpoints carry the chord, so their curve family is translation-equivariant
    and the momentum is kept to round-off; a free-endpoint network has no output bias, its
    family is not, and the momentum is kept only to the accuracy of the step."""
    problem = problems.toda_lattice(n=4)
    drifts = {}
    for label, method in FORMULATIONS:
        solver = method(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8))
        drifts[label] = invariant_drift(problem, solver, "momentum", 100)
        figure(f"Toda N=4 total momentum drift, {label} S=10 GL8, 100 steps", drifts[label])
    assert drifts["ShallowNetAutodiff"] <= 1e-12
    assert drifts["ShallowNet"] <= 1e-8


@pytest.mark.long
def test_noether_kepler_angular_momentum():
    """Rotations mix the coordinates, whose networks are independent: no formulation's curve
    family is rotation-equivariant, so the angular momentum is kept to the step's accuracy."""
    problem = problems.kepler()
    for label, method in FORMULATIONS:
        solver = method(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8))
        drift = invariant_drift(problem, solver, "angular_momentum", 100)
        figure(f"Kepler e=0.5 angular momentum drift, {label} S=10 GL8, 100 steps", drift)
        assert drift <= 1e-8


# -- precision ------------------------------------------------------------------------------


@pytest.mark.parametrize("method", ["ShallowNetAutodiffReversible"])
def test_float32_step_jaxpr_has_no_float64(method):
    # (ShallowNet on the oscillator is `tests/test_solver.py`; this one found a float64 grid
    # in the interpolating formulation's seed targets.)
    problem = problems.henon_heiles(dtype=jnp.float32)
    solver = getattr(dvi, method)(dvi.ShallowNetBasis(dvi.tanh, 6), dvi.GaussLegendre(6))
    t0, t1 = jnp.float32(0.0), jnp.float32(0.1)
    state = solver.init(problem.term, t0, t1, problem.y0, None)
    jaxpr = jax.make_jaxpr(
        lambda y, s: solver.step(problem.term, t0, t1, y, None, s, False)
    )(problem.y0, state)
    text = str(jaxpr)
    assert "f32" in text and "f64" not in text
