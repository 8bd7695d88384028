"""Small fully connected networks: forward pass and analytic backward pass, vectorised over rows.

A network maps ``n_in`` (normalised) features to one output through any list of hidden
layers with ``tanh`` activations (paper Sect. 3.4). The output activation is ``identity``
for point estimates, followed by a fixed affine map ``out_loc + out_scale * z`` (so that the
trained parameters live on a scale of order one whatever the target's units), or
``sigmoid4`` = 1/(1+exp(-4z)) for weights.

All parameters (weights and biases of every layer) are packed into one flat float64 vector,
layer after layer, each layer as ``W`` (``n_in x n_out``, row-major) then ``b`` (``n_out``).
Internally rows are processed in a column layout (``features x rows``) and in chunks that fit
in the CPU cache; the backward pass reuses the activations stored by the forward pass.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

#: Rows processed at once (column layout): small enough to stay in the CPU cache.
CHUNK = 16384

HIDDEN_ACTIVATION = "tanh"
OUTPUT_ACTIVATIONS = ("identity", "sigmoid4")


def sigmoid4(z: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """The weight output activation 1/(1+exp(-4z)), computed without overflow warnings."""
    out = np.multiply(z, -4.0, out=out)
    np.clip(out, -700.0, 700.0, out=out)
    np.exp(out, out=out)
    out += 1.0
    np.reciprocal(out, out=out)
    return out


@dataclass(frozen=True)
class Network:
    """Architecture of a network: ``n_in`` inputs, ``hidden`` sizes, one output.

    ``out_loc``/``out_scale`` define the fixed affine map after an identity output.
    """

    n_in: int
    hidden: tuple[int, ...]
    output: str = "identity"
    out_loc: float = 0.0
    out_scale: float = 1.0
    shapes: tuple[tuple[int, int], ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.n_in < 1:
            raise ValueError("a network needs at least one input")
        if any(int(h) < 1 for h in self.hidden):
            raise ValueError(f"hidden layer sizes must be positive, got {list(self.hidden)}")
        if self.output not in OUTPUT_ACTIVATIONS:
            raise ValueError(f"unknown output activation {self.output!r}")
        sizes = [int(self.n_in), *(int(h) for h in self.hidden), 1]
        object.__setattr__(self, "hidden", tuple(int(h) for h in self.hidden))
        object.__setattr__(self, "shapes", tuple(zip(sizes[:-1], sizes[1:])))

    @property
    def activations(self) -> list[str]:
        """Activation of each layer (hidden layers, then the output layer)."""
        return [HIDDEN_ACTIVATION] * len(self.hidden) + [self.output]

    @property
    def n_params(self) -> int:
        return sum(i * o + o for i, o in self.shapes)

    # ---------------------------------------------------------------- parameters
    def unpack(self, params: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Views ``[(W, b), ...]`` into the flat parameter vector (``W`` is ``n_in x n_out``)."""
        params = np.asarray(params, dtype=np.float64)
        if params.shape != (self.n_params,):
            raise ValueError(f"expected {self.n_params} parameters, got shape {params.shape}")
        layers, k = [], 0
        for i, o in self.shapes:
            w = params[k : k + i * o].reshape(i, o)
            k += i * o
            layers.append((w, params[k : k + o]))
            k += o
        return layers

    def pack(self, layers: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        """Flat parameter vector from ``[(W, b), ...]``."""
        if len(layers) != len(self.shapes):
            raise ValueError(f"expected {len(self.shapes)} layers, got {len(layers)}")
        parts = []
        for (w, b), (i, o) in zip(layers, self.shapes):
            w = np.asarray(w, dtype=np.float64)
            b = np.asarray(b, dtype=np.float64).reshape(-1)
            if w.shape != (i, o) or b.shape != (o,):
                raise ValueError(f"layer shapes {w.shape}, {b.shape} do not match ({i}, {o})")
            parts += [w.ravel(), b]
        return np.concatenate(parts)

    def init_normal(self, rng: np.random.Generator, sigma: float = 0.1) -> np.ndarray:
        """All weights and biases drawn from N(0, sigma) (paper Sect. 3.4)."""
        return rng.normal(0.0, sigma, self.n_params)

    def init_identity(
        self,
        rng: np.random.Generator,
        feature: int,
        in_loc: np.ndarray,
        in_scale: np.ndarray,
        sigma: float = 0.01,
        gain: float = 0.1,
    ) -> np.ndarray:
        """Near-identity start: the output approximately equals the raw input ``feature``.

        The normalised feature is passed through node 0 of every hidden layer with a small
        gain (where tanh is nearly linear); the output layer undoes the gain and both
        normalisations. Small N(0, sigma) noise is added everywhere else.
        """
        if self.output != "identity":
            raise ValueError("the identity initialisation is for point-estimate networks")
        layers = self.unpack(self.init_normal(rng, sigma).copy())
        for idx, (w, b) in enumerate(layers[:-1]):
            w[:, 0] = 0.0
            b[0] = 0.0
            w[feature if idx == 0 else 0, 0] = gain if idx == 0 else 1.0
        w, b = layers[-1]
        w[:, 0] = 0.0
        w[0, 0] = in_scale[feature] / (gain * self.out_scale)
        b[0] = (in_loc[feature] - self.out_loc) / self.out_scale
        return self.pack(layers)

    # ---------------------------------------------------------------- passes
    def _layers(self, params: np.ndarray, dtype: np.dtype) -> list[tuple[np.ndarray, np.ndarray]]:
        return [(w.astype(dtype), b.astype(dtype)) for w, b in self.unpack(params)]

    def forward(self, params: np.ndarray, xt: np.ndarray) -> np.ndarray:
        """Outputs (``n_rows``) for inputs in column layout ``xt`` (``n_in x n_rows``).

        The arithmetic is done in the precision of ``xt`` (float64 or float32).
        """
        layers = self._layers(params, xt.dtype)
        n = xt.shape[1]
        out = np.empty(n, dtype=xt.dtype)
        for s in range(0, n, CHUNK):
            a = xt[:, s : s + CHUNK]
            for w, b in layers[:-1]:
                a = _hidden(w, b, a)
            out[s : s + CHUNK] = self._output(layers[-1], a)
        return out

    def forward_cached(
        self, params: np.ndarray, xt: np.ndarray, work: list[list[np.ndarray]] | None = None
    ) -> tuple[np.ndarray, list[list[np.ndarray]]]:
        """Like :meth:`forward`, also returning the activations of each chunk.

        ``work`` is a cache returned by an earlier call on the same ``xt``: its buffers are
        reused (allocating fresh memory on every call costs more than the arithmetic).
        """
        layers = self._layers(params, xt.dtype)
        n = xt.shape[1]
        out = np.empty(n, dtype=xt.dtype)
        cache: list[list[np.ndarray]] = []
        for ci, s in enumerate(range(0, n, CHUNK)):
            acts = [xt[:, s : s + CHUNK]]
            for li, (w, b) in enumerate(layers[:-1]):
                buf = None if work is None else work[ci][li + 1]
                acts.append(_hidden(w, b, acts[-1], buf))
            out[s : s + CHUNK] = self._output(layers[-1], acts[-1])
            cache.append(acts)
        return out, cache

    def backward(
        self,
        params: np.ndarray,
        out: np.ndarray,
        cache: list[list[np.ndarray]],
        grad_out: np.ndarray,
    ) -> np.ndarray:
        """Gradient of a cost with respect to the flat parameters, given ``d cost / d output``.

        Computed in the precision of the cached activations, accumulated in float64.
        """
        dt = cache[0][0].dtype if cache else np.dtype(np.float64)
        layers = self._layers(params, dt)
        grad = np.zeros(self.n_params)
        glayers = self.unpack(grad)  # views into ``grad``
        n_hidden = len(layers) - 1
        tmp: list[np.ndarray] = []
        for ci, acts in enumerate(cache):
            s = ci * CHUNK
            c = acts[0].shape[1]
            if not tmp or tmp[0].shape[1] != c:
                tmp = [np.empty((h, c), dtype=dt) for h in (*self.hidden, *self.hidden)]
                ones = np.ones(c, dtype=dt)
            g = grad_out[s : s + c].astype(dt, copy=False)
            if self.output == "identity":
                gz = g * self.out_scale
            else:  # d sigmoid(4z)/dz = 4 s (1 - s)
                o = out[s : s + c]
                gz = g * 4.0 * o * (1.0 - o)
            gw, gb = glayers[-1]
            gw[:, 0] += acts[-1] @ gz
            gb[0] += gz.sum()
            if n_hidden == 0:
                continue
            ga = np.multiply(layers[-1][0][:, 0:1], gz, out=tmp[n_hidden + n_hidden - 1])
            for li in range(n_hidden - 1, -1, -1):
                a = acts[li + 1]
                gzl = np.multiply(a, a, out=tmp[li])
                np.subtract(1.0, gzl, out=gzl)
                gzl *= ga  # d tanh = 1 - a^2
                gw, gb = glayers[li]
                prev = acts[li]
                for i in range(prev.shape[0]):  # n_in gemv calls beat one skinny gemm
                    gw[i] += gzl @ prev[i]
                gb += gzl @ ones  # faster than .sum(axis=1)
                if li > 0:
                    ga = np.matmul(layers[li][0], gzl, out=tmp[n_hidden + li - 1])
        return grad

    def _output(self, layer: tuple[np.ndarray, np.ndarray], a: np.ndarray) -> np.ndarray:
        w, b = layer
        z = w[:, 0] @ a
        z += b[0]
        if self.output == "identity":
            if self.out_scale != 1.0:
                z *= z.dtype.type(self.out_scale)
            if self.out_loc != 0.0:
                z += self.out_loc
            return z
        return sigmoid4(z, out=z)


def _hidden(
    w: np.ndarray, b: np.ndarray, a: np.ndarray, out: np.ndarray | None = None
) -> np.ndarray:
    z = np.matmul(w.T, a, out=out)
    z += b[:, None]
    return np.tanh(z, out=z)
