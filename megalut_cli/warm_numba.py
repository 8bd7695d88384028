"""Imported by the worker server of commands whose workers run numba kernels.

numba sets up its CPU target (the registries of its typing and lowering, about 0.2 s of
CPU) at a process's first kernel call; done once in the server, the workers forked from it
start with it done (:data:`megalut_cli.cli.commands.WORKER_MODULES`).
"""

from numba.core.registry import cpu_target

cpu_target.target_context.refresh()
