"""The formulations of the variational step and what each needs: the step's equations, its
span, the Jacobian-free iteration on them, the constrained step, the checks of a step."""
