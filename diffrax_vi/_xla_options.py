"""An explicit opt-in for XLA's whole-loop compilation on the CPU.

XLA's CPU backend runs a compiled program as one kernel per fused operation, each with a fixed
cost, except inside a `while` loop whose one pass touches fewer bytes than
`xla_cpu_small_while_loop_byte_threshold`: such a loop is compiled as one function. Raising
that threshold is what makes a small system's step fast on a CPU (see the how-to on choosing a
solver). XLA reads the option once per process, from `XLA_FLAGS`, when JAX starts its backend,
so it is a setting of the whole process: the library never sets it unless asked to.
"""

from __future__ import annotations

import os
import re
import warnings

FLAG = "--xla_backend_extra_options"
THRESHOLD = "xla_cpu_small_while_loop_byte_threshold"
XLA_DEFAULT_BYTES = 1024  # XLA's own threshold: only the smallest loops are compiled whole
DEFAULT_BYTES = 100_000_000

# XLA splits XLA_FLAGS at white space; a value may be written in double quotes.
_TOKEN = re.compile(r'(?:[^\s"]|"[^"]*")+')
_EXTRA = re.compile(r"^--?xla_backend_extra_options=(.*)$", re.S)


def _tokens(flags: str) -> list[str]:
    return _TOKEN.findall(flags)


def _unquote(value: str) -> str:
    if len(value) >= 2 and value[0] == value[-1] == '"':
        return value[1:-1]
    return value


def _extra_options(token: str) -> list[str] | None:
    """The comma-separated entries of one `--xla_backend_extra_options=...` token, or `None`
    when the token is another flag."""
    match = _EXTRA.match(token)
    if match is None:
        return None
    return [entry for entry in _unquote(match.group(1)).split(",") if entry.strip()]


def _key(entry: str) -> str:
    return entry.split("=", 1)[0].strip()


def with_threshold(flags: str, threshold_bytes: int) -> str:
    """`flags` (the text of `XLA_FLAGS`) with the loop threshold set to `threshold_bytes`.

    Every other flag is kept as written. An existing `--xla_backend_extra_options=` value is
    extended with a comma (its last occurrence, the one XLA keeps), and a threshold already
    in it, in any occurrence, is replaced rather than repeated.
    """
    tokens = _tokens(flags)
    entry = f"{THRESHOLD}={int(threshold_bytes)}"
    last = None
    for i, token in enumerate(tokens):
        entries = _extra_options(token)
        if entries is None:
            continue
        kept = [e for e in entries if _key(e) != THRESHOLD]
        if len(kept) != len(entries):
            tokens[i] = f"{FLAG}={','.join(kept)}"
        last = i
    if last is None:
        tokens.append(f"{FLAG}={entry}")
    else:
        kept = _extra_options(tokens[last])
        tokens[last] = f"{FLAG}={','.join([*kept, entry])}"
    # An occurrence emptied of its only entry says nothing: drop it.
    return " ".join(t for t in tokens if _extra_options(t) != [])


def threshold_in(flags: str) -> int | None:
    """The loop threshold that `flags` (the text of `XLA_FLAGS`) sets, or `None`."""
    found = None
    for token in _tokens(flags):
        for entry in _extra_options(token) or ():
            if _key(entry) == THRESHOLD:
                try:
                    found = int(entry.split("=", 1)[1])
                except (IndexError, ValueError):
                    found = None
    return found


def _backend_started() -> bool | None:
    """Whether JAX has created its backends (`None` where this JAX version does not say).

    XLA parses `XLA_FLAGS` when the first backend is created; after that a change to the
    environment is never read again in this process.
    """
    try:
        from jax._src import xla_bridge
    except ImportError:
        return None
    started = getattr(xla_bridge, "backends_are_initialized", None)
    if callable(started):
        try:
            return bool(started())
        except Exception:
            pass
    backends = getattr(xla_bridge, "_backends", None)
    if isinstance(backends, dict):
        return len(backends) != 0
    return None


def compile_loops_whole(threshold_bytes: int = DEFAULT_BYTES) -> None:
    """Let XLA's CPU backend compile each small `while` loop, a solve's step loop among them, as
    one function, for the rest of this process.

    On a CPU the fixed cost of each of the hundred or so kernels in a small system's step,
    not its arithmetic, sets the time per step. XLA compiles a loop whole, without those
    costs, when one pass of it touches fewer than `threshold_bytes` bytes and it calls no
    library (LAPACK, the dot library, a host callback): with it a `CGVI` step on the
    Jacobian-free iteration is several times faster. It changes nothing on a GPU.

    This adds `--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=...` to the
    environment variable `XLA_FLAGS`, merged with the flags already there. XLA reads those
    flags once, when JAX starts its backend, so call this before the first JAX computation of
    the process (importing `jax` or `diffrax_vi` is fine). It is a setting of the whole
    process, not of one solve: every program compiled afterwards is compiled this way. The
    results agree with those of the default compilation to rounding, not to the bit, since
    XLA orders the arithmetic differently.

    **Arguments:**

    - `threshold_bytes`: the largest number of bytes one pass of a loop may touch for the loop
      to be compiled whole. XLA's own default covers only the smallest loops.

    **Returns:**

    Nothing; `diffrax_vi.loops_compiled_whole()` then reports `True`.

    **Raises:**

    `RuntimeError` if JAX has already started its backend with another threshold (any JAX
    computation starts it): the new setting could not take effect. Call this first, or set the
    variable where the process is started. Calling it again with the threshold already set
    is harmless.
    """
    if isinstance(threshold_bytes, bool) or int(threshold_bytes) != threshold_bytes:
        raise TypeError(f"threshold_bytes must be an integer, got {threshold_bytes!r}")
    threshold_bytes = int(threshold_bytes)
    if threshold_bytes < 0:
        raise ValueError(f"threshold_bytes must be non-negative, got {threshold_bytes}")
    flags = os.environ.get("XLA_FLAGS", "")
    if threshold_in(flags) == threshold_bytes:
        return
    line = f'XLA_FLAGS="{with_threshold(flags, threshold_bytes)}"'
    started = _backend_started()
    if started:
        raise RuntimeError(
            "compile_loops_whole() was called after JAX started its backend, which read "
            "XLA_FLAGS then and never reads it again, so it cannot take effect in this "
            "process. Call `diffrax_vi.compile_loops_whole()` before the first JAX computation "
            "(at the top of the script, after the imports), or start the process with the "
            f"environment variable set:\n    {line}"
        )
    if started is None:
        warnings.warn(
            "compile_loops_whole(): this JAX version does not say whether its backend has "
            "started; the option takes effect only if no JAX computation has run yet "
            f"(else start the process with {line})",
            RuntimeWarning,
            stacklevel=2,
        )
    os.environ["XLA_FLAGS"] = with_threshold(flags, threshold_bytes)


def loops_compiled_whole() -> bool:
    """Whether `XLA_FLAGS` asks XLA to compile loops whole: a loop threshold above XLA's own
    default.

    This reads the environment variable, as set by `diffrax_vi.compile_loops_whole()` or by the
    shell; it is in force if it was set before JAX started its backend.

    **Returns:**

    `True` if `XLA_FLAGS` sets `xla_cpu_small_while_loop_byte_threshold` above XLA's default.
    """
    threshold = threshold_in(os.environ.get("XLA_FLAGS", ""))
    return threshold is not None and threshold > XLA_DEFAULT_BYTES
