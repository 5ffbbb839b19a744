"""Explicit symplectic solvers for separable Lagrangians (kick-drift splittings, symmetric
compositions of Störmer-Verlet, RKN splittings) and RATTLE for holonomic constraints.

Private: the public names are exported from `diffrax_vi`.
"""
