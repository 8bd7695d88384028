"""Trained shear estimators: committees of networks and the self-describing HDF5 model file.

A :class:`ShearModel` holds point-estimate committees (``point``, one per target such as
``tru_g1``) and, after ``train-weight``, weight committees (``weight``). A
:class:`Committee` predicts the mean of its selected members. The file layout is
documented in ``docs/model-format.md``; it is plain HDF5 (datasets and attributes, JSON
strings for lists), never pickle, readable with ``h5py`` alone.
"""

from __future__ import annotations

import json
import logging
import os
import uuid as _uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from megalut_cli.atomic import atomic_output
from megalut_cli.errors import InputError
from megalut_cli.nn.network import Network, sigmoid4
from megalut_cli.nn.symmetry import SYMMETRIES, feature_signs, output_signs
from megalut_cli.provenance import CREATOR, sha256_file, utc_now

log = logging.getLogger(__name__)

FORMAT = "megalut.model"
#: The newest layout this megalut reads and writes; a model without ``symmetry`` is written
#: in the 1.0 layout (1.1 added the ``symmetry`` attribute).
FORMAT_VERSION = "1.1"
FORMAT_VERSION_PLAIN = "1.0"
KINDS = ("point", "weight")
HISTORY_COLUMNS = ["train", "valid"]

#: Rows per block in :meth:`Committee.predict` (keeps the intermediate arrays in cache).
PREDICT_CHUNK = 4096


def component_name(target: str) -> str:
    """HDF5 group name of a committee: the target without its ``tru_`` prefix (``g1``)."""
    return target[4:] if target.startswith("tru_") and len(target) > 4 else target


def prediction_column(target: str, kind: str = "point") -> str:
    """Catalog column of a prediction: ``pre_X`` for target ``tru_X``, ``pre_X_w`` for weights."""
    base = "pre_" + component_name(target)
    return base + "_w" if kind == "weight" else base


@dataclass
class Member:
    """One trained network of a committee and its training record."""

    layers: list[tuple[np.ndarray, np.ndarray]]  # [(W (n_in x n_out), b (n_out))]
    seed: int = 0
    keys: tuple[int, ...] = ()
    train_cost: float = float("nan")
    valid_cost: float = float("nan")
    n_iter: int = 0
    best_iter: int = 0
    selected: bool = True
    history: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))


class Committee:
    """A committee of networks for one target; predicts the mean of its selected members.

    ``kind`` is ``"point"`` (identity output then ``out_loc + out_scale * z``) or
    ``"weight"`` (sigmoid 1/(1+exp(-4z)) output). Inputs are normalised with
    ``(x - in_loc) / in_scale`` before the first layer.
    """

    def __init__(
        self,
        kind: str,
        target: str,
        features: Sequence[str],
        hidden: Sequence[int],
        in_loc: np.ndarray,
        in_scale: np.ndarray,
        members: Sequence[Member],
        out_loc: float = 0.0,
        out_scale: float = 1.0,
        cost: str = "msb",
        normalization: str = "minmax",
        training: Mapping[str, Any] | None = None,
    ) -> None:
        if kind not in KINDS:
            raise ValueError(f"unknown committee kind {kind!r}")
        self.kind = kind
        self.target = str(target)
        self.features = [str(f) for f in features]
        self.hidden = tuple(int(h) for h in hidden)
        self.in_loc = np.asarray(in_loc, dtype=np.float64).reshape(-1)
        self.in_scale = np.asarray(in_scale, dtype=np.float64).reshape(-1)
        self.out_loc = float(out_loc)
        self.out_scale = float(out_scale)
        self.cost = cost
        self.normalization = normalization
        self.training = dict(training or {})
        self.members = list(members)
        if len(self.in_loc) != len(self.features) or len(self.in_scale) != len(self.features):
            raise ValueError("normalisation does not match the number of features")
        net = self.network
        for m in self.members:
            net.pack(m.layers)  # checks shapes
        if not self.selected:
            raise ValueError(f"committee {self.target}: no selected member")
        self._build()

    # ------------------------------------------------------------------ properties
    @property
    def network(self) -> Network:
        """The architecture shared by all members."""
        output = "identity" if self.kind == "point" else "sigmoid4"
        return Network(len(self.features), self.hidden, output, self.out_loc, self.out_scale)

    @property
    def selected(self) -> list[Member]:
        return [m for m in self.members if m.selected]

    @property
    def n_selected(self) -> int:
        return len(self.selected)

    def member_params(self, i: int) -> np.ndarray:
        """Flat parameter vector of member ``i``."""
        return self.network.pack(self.members[i].layers)

    # ------------------------------------------------------------------ prediction
    def _build(self) -> None:
        """Stack the selected members into block matrices (all members in one pass).

        The input normalisation is folded into the first layer and, for point committees,
        the output affine map and the mean over members into the last one.
        """
        sel = self.selected
        m = len(sel)
        w0 = np.concatenate([mem.layers[0][0] for mem in sel], axis=1) / self.in_scale[:, None]
        b0 = np.concatenate([mem.layers[0][1] for mem in sel])
        b0 = b0 - (self.in_loc / self.in_scale) @ np.concatenate(
            [mem.layers[0][0] for mem in sel], axis=1
        )
        stack: list[tuple[np.ndarray, np.ndarray]] = [(w0, b0)]
        for li in range(1, len(self.hidden) + 1):
            hin, hout = sel[0].layers[li][0].shape
            w = np.zeros((m * hin, m * hout))
            for k, mem in enumerate(sel):
                w[k * hin : (k + 1) * hin, k * hout : (k + 1) * hout] = mem.layers[li][0]
            stack.append((w, np.concatenate([mem.layers[li][1] for mem in sel])))
        if self.kind == "point":  # mean of (out_loc + out_scale * z_k) folded into one column
            w, b = stack[-1]  # (m * h_last, m), block structure: one column per member
            w = w.sum(axis=1, keepdims=True) * (self.out_scale / m)
            stack[-1] = (w, np.atleast_1d(self.out_loc + self.out_scale * b.mean()))
        self._stack = [(np.ascontiguousarray(w), np.ascontiguousarray(b)) for w, b in stack]

    def predict(self, x: np.ndarray) -> np.ndarray:
        """Committee prediction for rows ``x`` (n x len(features)); NaN where an input is not
        finite."""
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != len(self.features):
            raise ValueError(f"expected an array of shape (n, {len(self.features)}), got {x.shape}")
        n = x.shape[0]
        out = np.empty(n)
        good = np.isfinite(x).all(axis=1)
        all_good = bool(good.all())
        if not all_good:
            x = np.where(good[:, None], x, 0.0)
        last = len(self._stack) - 1
        for s in range(0, n, PREDICT_CHUNK):
            a = x[s : s + PREDICT_CHUNK]
            for li, (w, b) in enumerate(self._stack):
                z = a @ w
                z += b
                if li < last:
                    a = np.tanh(z, out=z)
                elif self.kind == "point":
                    out[s : s + PREDICT_CHUNK] = z[:, 0]
                else:
                    out[s : s + PREDICT_CHUNK] = sigmoid4(z, out=z).mean(axis=1)
        if not all_good:
            out[~good] = np.nan
        return out

    # ------------------------------------------------------------------ HDF5
    def _write(self, g: Any) -> None:
        g.attrs["kind"] = self.kind
        g.attrs["target"] = self.target
        g.attrs["features"] = json.dumps(self.features)
        g.attrs["hidden"] = json.dumps(list(self.hidden))
        g.attrs["cost"] = self.cost
        g.attrs["combine"] = "mean"
        g.attrs["n_members"] = len(self.members)
        g.attrs["n_selected"] = self.n_selected
        g.attrs["training"] = json.dumps(self.training, sort_keys=True)
        nrm = g.create_group("normalization")
        nrm.attrs["method"] = self.normalization
        nrm.create_dataset("in_loc", data=self.in_loc)
        nrm.create_dataset("in_scale", data=self.in_scale)
        nrm.create_dataset("out_loc", data=self.out_loc)
        nrm.create_dataset("out_scale", data=self.out_scale)
        mg = g.create_group("members")
        hg = g.create_group("history")
        acts = self.network.activations
        for i, mem in enumerate(self.members):
            name = f"{i:03d}"
            sg = mg.create_group(name)
            sg.attrs["seed"] = int(mem.seed)
            sg.attrs["seed_keys"] = json.dumps([int(k) for k in mem.keys])
            sg.attrs["train_cost"] = float(mem.train_cost)
            sg.attrs["valid_cost"] = float(mem.valid_cost)
            sg.attrs["n_iter"] = int(mem.n_iter)
            sg.attrs["best_iter"] = int(mem.best_iter)
            sg.attrs["selected"] = bool(mem.selected)
            lg = sg.create_group("layers")
            for li, (w, b) in enumerate(mem.layers):
                layer = lg.create_group(str(li))
                layer.attrs["activation"] = acts[li]
                layer.create_dataset("W", data=np.asarray(w, dtype=np.float64))
                layer.create_dataset("b", data=np.asarray(b, dtype=np.float64))
            h = hg.create_dataset(
                name, data=np.asarray(mem.history, dtype=np.float64).reshape(-1, 2)
            )
            h.attrs["columns"] = json.dumps(HISTORY_COLUMNS)

    @classmethod
    def _read(cls, g: Any) -> Committee:
        features = json.loads(_attr(g, "features"))
        hidden = json.loads(_attr(g, "hidden"))
        nrm = g["normalization"]
        members = []
        n_layers = len(hidden) + 1
        for name in sorted(g["members"]):
            sg = g["members"][name]
            layers = [
                (
                    np.asarray(sg["layers"][str(li)]["W"][()], dtype=np.float64),
                    np.asarray(sg["layers"][str(li)]["b"][()], dtype=np.float64),
                )
                for li in range(n_layers)
            ]
            hist = (
                g["history"][name][()]
                if "history" in g and name in g["history"]
                else np.zeros((0, 2))
            )
            members.append(
                Member(
                    layers=layers,
                    seed=int(sg.attrs.get("seed", 0)),
                    keys=tuple(json.loads(_attr(sg, "seed_keys", "[]"))),
                    train_cost=float(sg.attrs.get("train_cost", np.nan)),
                    valid_cost=float(sg.attrs.get("valid_cost", np.nan)),
                    n_iter=int(sg.attrs.get("n_iter", 0)),
                    best_iter=int(sg.attrs.get("best_iter", 0)),
                    selected=bool(sg.attrs["selected"]),
                    history=np.asarray(hist, dtype=np.float64).reshape(-1, 2),
                )
            )
        return cls(
            kind=_attr(g, "kind"),
            target=_attr(g, "target"),
            features=features,
            hidden=hidden,
            in_loc=nrm["in_loc"][()],
            in_scale=nrm["in_scale"][()],
            out_loc=float(nrm["out_loc"][()]) if "out_loc" in nrm else 0.0,
            out_scale=float(nrm["out_scale"][()]) if "out_scale" in nrm else 1.0,
            members=members,
            cost=_attr(g, "cost", ""),
            normalization=_attr(nrm, "method", "minmax"),
            training=json.loads(_attr(g, "training", "{}")),
        )


def _attr(obj: Any, key: str, default: str | None = None) -> str:
    if key not in obj.attrs:
        if default is None:
            raise KeyError(f"attribute {key!r} of {obj.name}")
        return default
    val = obj.attrs[key]
    return val.decode() if isinstance(val, bytes) else str(val)


#: What a model's networks estimate from (root attribute ``shear_mode``; absent: the first):
#: the features of the stamps as they are, calibrated on simulations (the paper's mode), or
#: the features of metacal versions, calibrated by each galaxy's response (docs/metacal.md).
SHEAR_MODES = ("simulation", "metacal")


class ShearModel:
    """Point (and weight) committees for each target, with provenance."""

    def __init__(
        self,
        point: Mapping[str, Committee] | None = None,
        weight: Mapping[str, Committee] | None = None,
        provenance: Mapping[str, Any] | None = None,
    ) -> None:
        self.point: dict[str, Committee] = dict(point or {})
        self.weight: dict[str, Committee] = dict(weight or {})
        self.provenance: dict[str, Any] = dict(provenance or {})
        #: Recorded validations, e.g. ``real_galaxy_bias`` (``megalut_cli.nn.population``).
        self.validation: dict[str, Any] = {}
        self.sha256 = ""
        self.uuid = ""
        self.created = ""
        self.format_version = FORMAT_VERSION
        #: One of :data:`SHEAR_MODES`: the catalogs ``predict`` applies the model to.
        self.shear_mode = SHEAR_MODES[0]
        #: One of :data:`megalut_cli.nn.symmetry.SYMMETRIES`: the networks as trained, or
        #: averaged over the pixel grid's rotations and reflections.
        self.symmetry = SYMMETRIES[0]

    @property
    def features(self) -> list[str]:
        """Union of all committees' features, in order of first appearance."""
        out: list[str] = []
        for c in [*self.point.values(), *self.weight.values()]:
            out += [f for f in c.features if f not in out]
        return out

    @property
    def targets(self) -> list[str]:
        return list(self.point)

    def __repr__(self) -> str:
        return (
            f"ShearModel(point={list(self.point)}, weight={list(self.weight)}, "
            f"features={self.features})"
        )

    def for_mode(self, mode: str, why: str) -> ShearModel:
        """The same networks for catalogs of another shear mode (:data:`SHEAR_MODES`), with the
        source model's sha256 and ``why`` in the provenance (``mode_from``)."""
        if mode not in SHEAR_MODES:
            raise ValueError(f"unknown shear mode {mode!r} (known: {', '.join(SHEAR_MODES)})")
        return self._derived("shear_mode", mode, "mode_from", why)

    def with_symmetry(self, symmetry: str, why: str) -> ShearModel:
        """The same networks evaluated with ``symmetry`` (:data:`SYMMETRIES`), with the source
        model's sha256 and ``why`` in the provenance (``symmetry_from``)."""
        if symmetry not in SYMMETRIES:
            raise ValueError(f"unknown symmetry {symmetry!r} (known: {', '.join(SYMMETRIES)})")
        if symmetry != SYMMETRIES[0]:
            for kind, comms in (("point", self.point), ("weight", self.weight)):
                for comm in comms.values():
                    feature_signs(comm.features)
                    output_signs(comm.target, kind)
        return self._derived("symmetry", symmetry, "symmetry_from", why)

    def _derived(self, attr: str, value: str, record: str, why: str) -> ShearModel:
        """A copy with ``attr`` set to ``value``; the source's ``attr``, sha256 and uuid and
        ``why`` in the provenance under ``record``."""
        out = ShearModel(self.point, self.weight, self.provenance)
        out.validation = dict(self.validation)
        out.shear_mode, out.symmetry = self.shear_mode, self.symmetry
        out.provenance[record] = {
            attr: getattr(self, attr),
            "sha256": self.sha256,
            "uuid": self.uuid,
            "why": why,
        }
        setattr(out, attr, value)
        return out

    # ------------------------------------------------------------------ I/O
    def save(self, path: str | os.PathLike, overwrite: bool = False) -> None:
        """Write the model atomically (temporary file + rename); sets ``sha256``."""
        import h5py

        for kind, comms in (("point", self.point), ("weight", self.weight)):
            names = [component_name(t) for t in comms]
            if len(set(names)) != len(names):
                raise ValueError(f"{kind} committees have clashing component names {names}")
        self.uuid = str(_uuid.uuid4())
        self.created = utc_now()
        with atomic_output(path, overwrite) as tmp:
            with h5py.File(tmp, "w") as f:
                f.attrs["format"] = FORMAT
                f.attrs["format_version"] = (
                    FORMAT_VERSION if self.symmetry != SYMMETRIES[0] else FORMAT_VERSION_PLAIN
                )
                f.attrs["creator"] = CREATOR
                f.attrs["created"] = self.created
                f.attrs["uuid"] = self.uuid
                f.attrs["shear_mode"] = self.shear_mode
                if self.symmetry != SYMMETRIES[0]:
                    f.attrs["symmetry"] = self.symmetry
                for kind, comms in (("point", self.point), ("weight", self.weight)):
                    kg = f.create_group(kind)
                    for target, comm in comms.items():
                        comm._write(kg.create_group(component_name(target)))
                prov = f.create_group("provenance")
                for key, val in self.provenance.items():
                    prov.attrs[key] = (
                        val if isinstance(val, str) else json.dumps(val, sort_keys=True)
                    )
                if self.validation:
                    val_group = f.create_group("validation")
                    for key, val in self.validation.items():
                        val_group.attrs[key] = json.dumps(val, sort_keys=True)
        self.sha256 = sha256_file(path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> ShearModel:
        """Read a model file; :class:`InputError` if it is not one of ours, truncated, or too
        new."""
        import h5py

        p = Path(path)
        if not p.is_file():
            raise InputError(f"{p}: no such model file")
        try:
            f = h5py.File(p, "r")
        except OSError:
            raise InputError(
                f"{p}: not a readable HDF5 model file (truncated or not HDF5)"
            ) from None
        try:
            with f:
                fmt = f.attrs.get("format")
                fmt = fmt.decode() if isinstance(fmt, bytes) else fmt
                if fmt != FORMAT:
                    raise InputError(f"{p}: not a megalut model file (format attribute {fmt!r})")
                version = _attr(f, "format_version", "")
                major, minor = _parse_version(version, p)
                cur_major, cur_minor = _parse_version(FORMAT_VERSION, p)
                if major != cur_major:
                    raise InputError(
                        f"{p}: model format version {version} is not supported "
                        f"(this megalut reads {cur_major}.x)"
                    )
                if minor > cur_minor:
                    log.warning(
                        "%s: model format version %s is newer than this megalut's %s",
                        p,
                        version,
                        FORMAT_VERSION,
                    )
                model = cls()
                model.format_version = version
                for kind in KINDS:
                    comms = {}
                    for name in f.get(kind, {}):
                        comm = Committee._read(f[kind][name])
                        comms[comm.target] = comm
                    setattr(model, kind, comms)
                if not model.point and not model.weight:
                    raise InputError(f"{p}: the model holds no committee")
                if "provenance" in f:
                    for key, val in f["provenance"].attrs.items():
                        val = val.decode() if isinstance(val, bytes) else str(val)
                        try:
                            model.provenance[key] = json.loads(val)
                        except json.JSONDecodeError:
                            model.provenance[key] = val
                for key, val in f["validation"].attrs.items() if "validation" in f else ():
                    model.validation[key] = json.loads(
                        val.decode() if isinstance(val, bytes) else str(val)
                    )
                model.uuid = _attr(f, "uuid", "")
                model.created = _attr(f, "created", "")
                model.shear_mode = _attr(f, "shear_mode", SHEAR_MODES[0])
                model.symmetry = _attr(f, "symmetry", SYMMETRIES[0])
                if model.symmetry not in SYMMETRIES:
                    raise InputError(
                        f"{p}: unknown symmetry {model.symmetry!r} (known: {', '.join(SYMMETRIES)})"
                    )
                if model.shear_mode not in SHEAR_MODES:
                    raise InputError(
                        f"{p}: unknown shear_mode {model.shear_mode!r} "
                        f"(known: {', '.join(SHEAR_MODES)})"
                    )
        except InputError:
            raise
        except (KeyError, ValueError, TypeError, OSError, json.JSONDecodeError) as err:
            raise InputError(f"{p}: truncated or corrupt model file ({err})") from None
        model.sha256 = sha256_file(p)
        return model


def _parse_version(version: str, path: Path) -> tuple[int, int]:
    try:
        major, minor = (int(v) for v in str(version).split(".")[:2])
    except ValueError:
        raise InputError(f"{path}: unreadable model format version {version!r}") from None
    return major, minor
