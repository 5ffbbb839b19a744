"""Benchmark and study tools: measure the integrator and its parts on your own problems.

- `seed_quality`: the OGA seed on its own (no integrator), over every configuration.
"""
