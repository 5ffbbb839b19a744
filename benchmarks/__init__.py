"""The scripts behind the figures of the documentation, one module each.

Run one from the repository root as `python -m benchmarks.<name> [--help]`; `benchmarks/README.md`
lists them with the results they wrote and the pages that quote those results. Helpers that
more than one script uses live in `benchmarks.common`.
"""
