"""Lagrangian terms and ansätze written with sympy (imported only when one of these is used).

- `terms`: Lagrangian terms from a sympy expression (`sympy_lagrangian_term`,
  `SympyLagrangianTerm`), built on `diffrax_vi._terms`.
- `ansatz`: user-written ansätze in absolute time (`SymbolicAnsatz`, `VISEBasis`), built on
  `diffrax_vi._ansatz.base`.

Both compile their expressions with `diffrax_vi._codegen`, whose two user-facing functions this
package re-exports. The public names are those of `diffrax_vi` (loaded lazily there).
"""

from .._codegen import compile_exprs as compile_exprs
from .._codegen import sympy_activation as sympy_activation
