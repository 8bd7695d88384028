"""Imported by the worker server of commands whose workers run numba kernels: what those
kernels need before their first call is set up once in the server, so the workers forked
from it start with it done (:data:`megalut_cli.cli.commands.WORKER_MODULES`)."""

from megalut_cli.jit import prepare_runtime

prepare_runtime()
