"""Everything written with sympy (imported only when one of these is used).

- `codegen`: sympy expressions compiled to JAX (`compile_exprs`) and the closed-form derivative
  kernels of the network ansätze (`curve_function`, `symbolic_*_evaluate`); it depends on the
  activations alone, so the ansätze can use it.
- `terms`: Lagrangian terms from a sympy expression (`sympy_lagrangian_term`,
  `SympyLagrangianTerm`), built on `diffrax_vi.terms`.
- `ansatz`: user-written ansätze in absolute time (`SymbolicAnsatz`, `VISEBasis`), built on
  `diffrax_vi.ansatz.base`.

This package re-exports `codegen`; `terms` and `ansatz` are imported as submodules (or through
the lazy names of `diffrax_vi`), so that using the kernels does not load the terms.
"""

from .codegen import CurveKernels as CurveKernels
from .codegen import compile_exprs as compile_exprs
from .codegen import curve_function as curve_function
from .codegen import curve_kernels as curve_kernels
from .codegen import dense_expression as dense_expression
from .codegen import shallow_neuron_expression as shallow_neuron_expression
from .codegen import symbolic_curve_evaluate as symbolic_curve_evaluate
from .codegen import symbolic_dense_evaluate as symbolic_dense_evaluate
from .codegen import symbolic_shallow_evaluate as symbolic_shallow_evaluate
from .codegen import sympy_activation as sympy_activation
