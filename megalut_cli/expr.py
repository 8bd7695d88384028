"""Safe selection expressions over catalog columns (never ``eval`` of user text).

Row expressions select realizations, e.g. ``"snr > 10 & adamom_sigma > 1.5"``.
Case expressions select whole cases from per-case aggregates, e.g. ``"mean(snr) > 10"``.

Grammar: numbers, column names, ``+ - * / ** %``, comparisons (chainable), ``& | ~``
(also ``and or not``), parentheses, and the functions ``abs sqrt log log10 exp
isfinite isnan`` plus, in case expressions, the aggregates ``mean median min max sum
std count frac`` (``frac(x)`` is the fraction of rows where ``x`` holds). Aggregates skip
non-finite values. A bare column in a case expression must be constant within each case
(a true parameter such as ``tru_rad``). Numeric expressions (no comparison) are
quantities, e.g. for the ``--by`` of ``megalut evaluate``: ``sqrt(tru_e1**2 + tru_e2**2)``
per row, ``mean(snr)`` per case.
"""

from __future__ import annotations

import ast
import re
from collections.abc import Callable, Mapping

import numpy as np

from megalut_cli.errors import ConfigError

_FUNCS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "abs": np.abs,
    "sqrt": np.sqrt,
    "log": np.log,
    "log10": np.log10,
    "exp": np.exp,
    "isfinite": np.isfinite,
    "isnan": np.isnan,
}
_AGGS = ("mean", "median", "min", "max", "sum", "std", "count", "frac")

_BINOPS = {
    ast.Add: np.add,
    ast.Sub: np.subtract,
    ast.Mult: np.multiply,
    ast.Div: np.true_divide,
    ast.Pow: np.power,
    ast.Mod: np.mod,
    ast.BitAnd: np.logical_and,
    ast.BitOr: np.logical_or,
}
_CMPOPS = {
    ast.Lt: np.less,
    ast.LtE: np.less_equal,
    ast.Gt: np.greater,
    ast.GtE: np.greater_equal,
    ast.Eq: np.equal,
    ast.NotEq: np.not_equal,
}


def _parse(expr: str) -> ast.AST:
    if not isinstance(expr, str) or not expr.strip():
        raise ConfigError("empty selection expression")
    # ``&``, ``|`` and ``~`` bind like ``and``, ``or`` and ``not`` (looser than comparisons),
    # so that "snr > 10 & adamom_sigma > 1.5" means what it says. The grammar has no
    # strings, so a plain replacement is safe.
    text = expr.strip().replace("&", " and ").replace("|", " or ").replace("~", " not ").strip()
    try:
        return ast.parse(text, mode="eval").body
    except SyntaxError:
        hint = (
            " (compare with ==, not =)"
            if "=" in expr and "==" not in expr and not re.search(r"[<>!]=", expr)
            else ""
        )
        raise ConfigError(
            f"selection expression {expr!r} cannot be read{hint}: write conditions such as "
            '"snr > 10 & adamom_sigma > 1.5" or, per case, "mean(snr) > 10"'
        ) from None


#: Plain words for the Python syntax that expressions do not allow.
_SYNTAX_WORDS = {
    "Attribute": "'.' after a name (attribute access)",
    "Subscript": "'[ ]' (indexing)",
    "Tuple": "',' (tuples)",
    "List": "'[ ]' (lists)",
    "Dict": "'{ }' (dictionaries)",
    "Set": "'{ }' (sets)",
    "Lambda": "lambda",
    "Call": "a call of something other than a function name",
    "IfExp": "if/else",
    "Starred": "'*' before a name",
    "NamedExpr": "':='",
    "JoinedStr": "strings",
    "ListComp": "comprehensions",
    "GeneratorExp": "comprehensions",
    "MatMult": "'@'",
    "FloorDiv": "'//'",
    "LShift": "'<<'",
    "RShift": "'>>'",
    "BitXor": "'^'",
    "Is": "'is'",
    "IsNot": "'is not'",
    "In": "'in'",
    "NotIn": "'not in'",
}
_GRAMMAR = (
    "numbers, column names, + - * / ** %, comparisons, & | ~ (and, or, not), parentheses and the "
    "functions " + " ".join(_FUNCS)
)


def describe_syntax(node: ast.AST) -> str:
    """What a piece of unsupported syntax is, in words (never the parser's tree)."""
    name = type(node).__name__
    return _SYNTAX_WORDS.get(name, name.lower())


def unknown_columns_message(expr: str, missing: list[str], available: list[str]) -> str:
    """``unknown column(s) ...``, with close matches and the columns that exist."""
    import difflib

    close = {m: difflib.get_close_matches(m, available, n=1) for m in missing}
    guesses = [c[0] if len(missing) == 1 else f"{c[0]} for {m}" for m, c in close.items() if c]
    shown = ", ".join(sorted(available)[:40]) + (", ..." if len(available) > 40 else "")
    return (
        f"selection expression {expr!r}: unknown column(s) {', '.join(missing)}"
        + (f" (did you mean {'; '.join(guesses)}?)" if guesses else "")
        + f"; the catalog has: {shown}"
    )


def columns_used(expr: str) -> list[str]:
    """Column names an expression refers to, in order of appearance."""
    nodes = [
        n
        for n in ast.walk(_parse(expr))
        if isinstance(n, ast.Name) and n.id not in _FUNCS and n.id not in _AGGS
    ]
    names: list[str] = []
    for node in sorted(nodes, key=lambda n: n.col_offset):
        if node.id not in names:
            names.append(node.id)
    return names


class _Evaluator:
    def __init__(
        self,
        expr: str,
        columns: Mapping[str, np.ndarray],
        case_index: np.ndarray | None,
        n_cases: int,
    ):
        self.expr = expr
        self.columns = columns
        self.case_index = case_index  # per-row index of its case (0..n_cases-1), case mode only
        self.n_cases = n_cases

    def fail(self, what: str) -> ConfigError:
        return ConfigError(f"selection expression {self.expr!r}: {what}")

    def column(self, name: str) -> np.ndarray:
        if name not in self.columns:
            raise ConfigError(unknown_columns_message(self.expr, [name], list(self.columns)))
        return np.asarray(self.columns[name])

    def eval(self, node: ast.AST, in_agg: bool = False) -> np.ndarray:
        case_mode = self.case_index is not None
        if isinstance(node, ast.Constant):
            if isinstance(node.value, bool) or not isinstance(node.value, (int, float)):
                raise self.fail(f"unsupported constant {node.value!r}")
            return np.asarray(node.value)
        if isinstance(node, ast.Name):
            if node.id in ("True", "False"):
                return np.asarray(node.id == "True")
            col = self.column(node.id)
            if case_mode and not in_agg:
                return self._constant_per_case(node.id, col)
            return col
        if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            return _BINOPS[type(node.op)](
                self.eval(node.left, in_agg), self.eval(node.right, in_agg)
            )
        if isinstance(node, ast.UnaryOp):
            val = self.eval(node.operand, in_agg)
            if isinstance(node.op, ast.USub):
                return -val
            if isinstance(node.op, ast.UAdd):
                return +val
            if isinstance(node.op, (ast.Invert, ast.Not)):
                return np.logical_not(val)
        if isinstance(node, ast.BoolOp):
            op = np.logical_and if isinstance(node.op, ast.And) else np.logical_or
            out = self.eval(node.values[0], in_agg)
            for v in node.values[1:]:
                out = op(out, self.eval(v, in_agg))
            return out
        if isinstance(node, ast.Compare):
            left = self.eval(node.left, in_agg)
            result = np.asarray(True)
            for op, comp in zip(node.ops, node.comparators):
                if type(op) not in _CMPOPS:
                    raise self.fail(f"{describe_syntax(op)} is not allowed; use < <= > >= == !=")
                right = self.eval(comp, in_agg)
                result = np.logical_and(result, _CMPOPS[type(op)](left, right))
                left = right
            return result
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and not node.keywords:
            name = node.func.id
            if len(node.args) != 1:
                raise self.fail(f"{name}() takes exactly one argument")
            if name in _FUNCS:
                return _FUNCS[name](self.eval(node.args[0], in_agg))
            if name in _AGGS:
                if not case_mode:
                    raise self.fail(f"aggregate {name}() is only allowed in case selections")
                if in_agg:
                    raise self.fail("nested aggregates are not allowed")
                return self._aggregate(name, self.eval(node.args[0], in_agg=True))
            raise self.fail(
                f"unknown function {name!r}; functions: {' '.join(_FUNCS)}"
                + (f", aggregates: {' '.join(_AGGS)}" if case_mode else "")
            )
        bad = node.op if isinstance(node, ast.BinOp) else node
        raise self.fail(f"{describe_syntax(bad)} is not allowed; use {_GRAMMAR}")

    def _constant_per_case(self, name: str, col: np.ndarray) -> np.ndarray:
        idx = self.case_index
        first = np.full(self.n_cases, np.nan)
        first[idx[::-1]] = col[::-1]  # first value of each case
        if np.any(col != first[idx]):
            raise self.fail(
                f"column {name!r} varies within cases; use an aggregate such as mean({name})"
            )
        return first

    def _aggregate(self, name: str, values: np.ndarray) -> np.ndarray:
        idx = self.case_index
        n = self.n_cases
        values = np.broadcast_to(np.asarray(values, dtype=float), idx.shape)
        if name == "frac":
            good = np.isfinite(values)
            return np.bincount(
                idx, weights=np.where(good, values != 0, 0.0), minlength=n
            ) / np.maximum(np.bincount(idx, minlength=n), 1)
        good = np.isfinite(values)
        cnt = np.bincount(idx, weights=good, minlength=n)
        if name == "count":
            return cnt
        v = np.where(good, values, 0.0)
        s = np.bincount(idx, weights=v, minlength=n)
        with np.errstate(invalid="ignore", divide="ignore"):
            if name == "sum":
                return s
            mean = s / cnt
            if name == "mean":
                return mean
            if name == "std":
                s2 = np.bincount(idx, weights=v * v, minlength=n)
                return np.sqrt(np.maximum(s2 / cnt - mean**2, 0.0))
        order = np.lexsort((values, ~good, idx))  # per case: finite values sorted first
        out = np.full(n, np.nan)
        starts = np.searchsorted(idx[order], np.arange(n))
        for k in range(n):  # median/min/max: small loop over cases, vectorised inside
            c = int(cnt[k])
            if c == 0:
                continue
            seg = values[order[starts[k] : starts[k] + c]]
            out[k] = seg[0] if name == "min" else seg[-1] if name == "max" else np.median(seg)
        return out


def evaluate_rows(
    expr: str, columns: Mapping[str, np.ndarray], n_rows: int | None = None
) -> np.ndarray:
    """Boolean mask of the rows selected by ``expr``."""
    node = _parse(expr)
    if n_rows is None:
        n_rows = len(next(iter(columns.values()))) if columns else 0
    out = _Evaluator(expr, columns, None, 0).eval(node)
    if out.dtype != bool:
        raise ConfigError(f"selection expression {expr!r} is not a condition (use <, >, ==, ...)")
    return np.broadcast_to(out, (n_rows,)).copy()


def _eval_per_case(
    expr: str, columns: Mapping[str, np.ndarray], case: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    ids, index = np.unique(np.asarray(case), return_inverse=True)
    return ids, _Evaluator(expr, columns, index.ravel(), len(ids)).eval(_parse(expr))


def evaluate_cases(
    expr: str, columns: Mapping[str, np.ndarray], case: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Evaluate a case expression; returns ``(unique_case_ids, selected_mask)``."""
    ids, out = _eval_per_case(expr, columns, case)
    if out.dtype != bool:
        raise ConfigError(f"case selection {expr!r} is not a condition (use <, >, ==, ...)")
    return ids, np.broadcast_to(out, ids.shape).copy()


def uses_aggregate(expr: str) -> bool:
    """Whether ``expr`` calls a per-case aggregate (``mean(snr)``): then it is a case expression."""
    return any(
        isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id in _AGGS
        for n in ast.walk(_parse(expr))
    )


def check_quantity(expr: str, available: list[str] | None = None) -> bool:
    """Validate a numeric expression (not a condition); returns whether it is a case expression."""
    case_mode = uses_aggregate(expr)
    check_expression(expr, available, case_mode=case_mode)
    node = _parse(expr)
    cond = (
        isinstance(node, (ast.Compare, ast.BoolOp))
        or (isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.Not, ast.Invert)))
        or (isinstance(node, ast.Call) and getattr(node.func, "id", "") in ("isfinite", "isnan"))
    )
    if cond:
        raise ConfigError(f"expression {expr!r} is a condition, not a quantity")
    return case_mode


def _numeric(out: np.ndarray, expr: str) -> np.ndarray:
    if out.dtype == bool:
        raise ConfigError(f"expression {expr!r} is a condition, not a quantity")
    return np.asarray(out, dtype=float)


def evaluate_row_values(expr: str, columns: Mapping[str, np.ndarray], n_rows: int) -> np.ndarray:
    """Value of the numeric row expression ``expr`` (e.g. ``sqrt(tru_e1**2 + tru_e2**2)``) on
    each row."""
    out = _Evaluator(expr, columns, None, 0).eval(_parse(expr))
    return np.broadcast_to(_numeric(out, expr), (n_rows,)).copy()


def evaluate_case_values(
    expr: str, columns: Mapping[str, np.ndarray], case: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Value of the numeric case expression ``expr`` (e.g. ``mean(snr)``); returns
    ``(unique_case_ids, values)``."""
    ids, out = _eval_per_case(expr, columns, case)
    return ids, np.broadcast_to(_numeric(out, expr), ids.shape).copy()


def check_expression(
    expr: str, available: list[str] | None = None, case_mode: bool = False
) -> None:
    """Validate syntax and column names early (before any heavy work)."""
    node = _parse(expr)
    for sub in ast.walk(node):
        if isinstance(sub, ast.Call):
            if not isinstance(sub.func, ast.Name) or sub.func.id not in (
                *_FUNCS,
                *(_AGGS if case_mode else ()),
            ):
                fname = getattr(sub.func, "id", "?")
                raise ConfigError(f"selection expression {expr!r}: unknown function {fname!r}")
        elif (
            not isinstance(
                sub,
                (
                    ast.Constant,
                    ast.Name,
                    ast.BinOp,
                    ast.UnaryOp,
                    ast.BoolOp,
                    ast.Compare,
                    ast.Load,
                    ast.operator,
                    ast.unaryop,
                    ast.boolop,
                    ast.cmpop,
                ),
            )
            or (isinstance(sub, ast.BinOp) and type(sub.op) not in _BINOPS)
            or (isinstance(sub, ast.Compare) and any(type(op) not in _CMPOPS for op in sub.ops))
        ):
            bad = (
                sub.op
                if isinstance(sub, ast.BinOp)
                else (
                    next(op for op in sub.ops if type(op) not in _CMPOPS)
                    if isinstance(sub, ast.Compare)
                    else sub
                )
            )
            raise ConfigError(
                f"selection expression {expr!r}: {describe_syntax(bad)} is not allowed; "
                f"use {_GRAMMAR}"
            )
    if available is not None:
        missing = [
            c for c in columns_used(expr) if c not in available and c not in ("True", "False")
        ]
        if missing:
            raise ConfigError(unknown_columns_message(expr, missing, list(available)))
