"""numba's ``njit`` for megalut's kernels: a kernel found in numba's cache loads with numba's
runtime alone, without the CPU-target refresh numba does first (~0.15 s of each command;
docs/engines.md, "Compilation"). ``MEGALUT_NUMBA_FULL_SETUP=1`` restores numba's loading.
:func:`prefetch`: LLVM's cache prefetch, for kernels."""

from __future__ import annotations

import os
import types
from collections.abc import Callable
from typing import Any

import numba
from llvmlite import ir
from numba import types as nbtypes
from numba.core import cgutils
from numba.core.runtime import rtsys
from numba.extending import intrinsic

#: Environment variable: set to 1 to load cached kernels with numba's full target refresh.
FULL_SETUP_VARIABLE = "MEGALUT_NUMBA_FULL_SETUP"
#: The methods of numba's function cache that :func:`load_cached_overload` relies on.
CACHE_METHODS = ("load_overload", "_load_overload", "_guard_against_spurious_io_errors")


def light_loading() -> bool:
    """Whether megalut's cached kernels load with numba's runtime alone (the default)."""
    return os.environ.get(FULL_SETUP_VARIABLE, "") in ("", "0")


def load_cached_overload(cache: Any, sig: Any, target_context: Any) -> Any:
    """numba's ``Cache.load_overload`` with the target refresh replaced by the runtime's
    initialisation (idempotent): the cached compile result, or None. Should the light load
    fail (a kernel needing what only the refresh sets up), numba's own loading is done."""
    rtsys.initialize(target_context)
    try:
        with cache._guard_against_spurious_io_errors():
            return cache._load_overload(sig, target_context)
    except Exception:  # numba's own loading, which raises what is really wrong, if anything
        target_context.refresh()
        with cache._guard_against_spurious_io_errors():
            return cache._load_overload(sig, target_context)


def njit(**options: Any) -> Callable[[Callable[..., Any]], Any]:
    """``numba.njit(**options)`` whose dispatcher loads its cached overloads lightly."""

    def decorate(func: Callable[..., Any]) -> Any:
        dispatcher = numba.njit(**options)(func)
        cache = getattr(dispatcher, "_cache", None)
        if light_loading() and all(hasattr(cache, name) for name in CACHE_METHODS):
            cache.load_overload = types.MethodType(load_cached_overload, cache)
        return dispatcher

    return decorate


def prepare_runtime() -> None:
    """Set up, in this process, what its cached kernels need before their first call: the
    runtime, or the whole CPU target under ``MEGALUT_NUMBA_FULL_SETUP`` (worker servers
    call it once, before they fork workers)."""
    from numba.core.registry import cpu_target

    if light_loading():
        rtsys.initialize(cpu_target.target_context)
    else:
        cpu_target.target_context.refresh()


@intrinsic
def prefetch(typingctx: Any, array: Any, row: Any, column: Any) -> Any:
    """Ask the CPU to bring ``array[row, column]`` (a 2-d array) into its caches without
    waiting for it (LLVM's ``prefetch``: a read, kept in every cache level): no effect on
    any value, and never a fault, even for an index outside the array."""
    if not isinstance(array, nbtypes.Array) or array.ndim != 2:
        return None
    sig = nbtypes.void(array, nbtypes.intp, nbtypes.intp)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        array_type = signature.args[0]
        data = context.make_array(array_type)(context, builder, args[0])
        address = cgutils.get_item_pointer(
            context, builder, array_type, data, [args[1], args[2]], wraparound=False
        )
        byte_pointer = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        function = cgutils.get_or_insert_function(
            builder.module,
            ir.FunctionType(ir.VoidType(), [byte_pointer, i32, i32, i32]),
            "llvm.prefetch.p0i8",
        )
        # read (0), highest locality (3), data cache (1)
        builder.call(
            function,
            [builder.bitcast(address, byte_pointer), i32(0), i32(3), i32(1)],
        )
        return context.get_dummy_value()

    return sig, codegen
