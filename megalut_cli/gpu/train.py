"""Costs and gradients of a committee member on the device (``train-* --device gpu``).

:class:`DeviceObjective` is :class:`megalut_cli.nn.train.Objective` with the rows on the
device: the network's forward pass, the MSE/MSB/MSWB cost (per-case sums as segment sums)
and, by JAX's reverse-mode autodiff, its gradient, in float64 (or the ``dtype`` of the
trainer's passes). The optimiser (scipy BFGS/L-BFGS), the mini-batches, the validation
monitor and every random draw stay on the host, unchanged: only the parameter vector goes
to the device and the cost and gradient come back, at each evaluation.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from megalut_cli.gpu import jax_device
from megalut_cli.nn.data import CaseData
from megalut_cli.nn.network import Network

jax.config.update("jax_enable_x64", True)


def forward(net: Network, params: jnp.ndarray, x: jnp.ndarray) -> jnp.ndarray:
    """Outputs (n_rows) of ``net`` for normalised inputs ``x`` (n_rows, n_in)."""
    a = x
    k = 0
    for li, (i, o) in enumerate(net.shapes):
        w = params[k : k + i * o].reshape(i, o).astype(x.dtype)
        k += i * o
        b = params[k : k + o].astype(x.dtype)
        k += o
        z = a @ w + b
        if li < len(net.shapes) - 1:
            a = jnp.tanh(z)
        else:
            a = z[:, 0]
    if net.output == "identity":
        return a * net.out_scale + net.out_loc
    return 1.0 / (1.0 + jnp.exp(jnp.clip(-4.0 * a, -700.0, 700.0)))


def cost(
    name: str,
    out: jnp.ndarray,
    case: jnp.ndarray,
    n: jnp.ndarray,
    t: jnp.ndarray,
    t_row: jnp.ndarray,
    point: jnp.ndarray | None,
) -> jnp.ndarray:
    """MSE, MSB or MSWB (``megalut_cli.nn.costs``) of outputs ``out`` on rows grouped by
    ``case``."""
    c = n.shape[0]
    out = out.astype(jnp.float64)
    seg = functools.partial(
        jax.ops.segment_sum, segment_ids=case, num_segments=c, indices_are_sorted=True
    )
    if name == "mse":
        d = out - t_row
        return jnp.sum(seg(d * d) / (c * n))
    if name == "msb":
        r = seg(out) / n - t
        return r @ r / c
    wsum = jnp.maximum(seg(out), np.finfo(float).tiny)
    r = seg(out * point) / wsum - t
    return r @ r / c


@functools.partial(jax.jit, static_argnames=("net", "name"))
def _value(params, x, case, n, t, t_row, point, net, name):
    return cost(name, forward(net, params, x), case, n, t, t_row, point)


@functools.partial(jax.jit, static_argnames=("net", "name"))
def _value_and_grad(params, x, case, n, t, t_row, point, net, name):
    return jax.value_and_grad(lambda p: cost(name, forward(net, p, x), case, n, t, t_row, point))(
        params
    )


class DeviceObjective:
    """The interface of :class:`megalut_cli.nn.train.Objective`, evaluated on the device."""

    def __init__(
        self,
        net: Network,
        cost: str,
        data: CaseData,
        j: int,
        in_loc: np.ndarray,
        in_scale: np.ndarray,
        cost_scale: float = 1.0,
        dtype: str = "float64",
    ) -> None:
        if cost == "mswb" and data.point is None:
            raise ValueError("MSWB needs point estimates")
        dev = jax_device()
        put = functools.partial(jax.device_put, device=dev)
        self.net = net
        self.cost = cost
        self.x = put(np.ascontiguousarray((data.x - in_loc) / in_scale, dtype=dtype))
        self.case = put(np.asarray(data.case, dtype=np.int64))
        self.n = put(np.bincount(data.case, minlength=data.n_cases).astype(np.float64))
        self.t = put(np.ascontiguousarray(data.targets[:, j], dtype=np.float64))
        self.t_row = put(np.ascontiguousarray(data.row_targets[:, j], dtype=np.float64))
        self.point = (
            None
            if data.point is None
            else put(np.ascontiguousarray(data.point[:, j], dtype=np.float64))
        )
        self.norm = 1.0 / float(cost_scale) ** 2
        self.n_evals = 0

    def _args(self, params: np.ndarray) -> tuple:
        return (
            jnp.asarray(params, dtype=jnp.float64),
            self.x,
            self.case,
            self.n,
            self.t,
            self.t_row,
            self.point,
        )

    def value(self, params: np.ndarray) -> float:
        """The cost (in the targets' units squared)."""
        self.n_evals += 1
        return float(_value(*self._args(params), net=self.net, name=self.cost))

    def value_and_grad(self, params: np.ndarray) -> tuple[float, np.ndarray]:
        """The cost and its gradient (autodiff), back on the host."""
        self.n_evals += 1
        v, g = _value_and_grad(*self._args(params), net=self.net, name=self.cost)
        return float(v), np.asarray(g, dtype=np.float64)

    def scaled(self, params: np.ndarray) -> float:
        return self.value(params) * self.norm

    def scaled_with_grad(self, params: np.ndarray) -> tuple[float, np.ndarray]:
        c, g = self.value_and_grad(params)
        return c * self.norm, g * self.norm
