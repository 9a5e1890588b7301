"""Numeric evaluation of CasADi SX functions, vectorised over a batch with NumPy.

A system is written once as CasADi SX expressions. The NLP uses them symbolically; the
simulator and the sampling planner evaluate the very same expression graph through the
NumPy code generated here (one Python statement per SX instruction), which is exact to
floating point and avoids CasADi's per-call conversion overhead for small batches. For a
single sample (the simulated plant) :func:`compile_one` generates the same statements on
Python floats, with the same numbers.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import casadi as ca
import numpy as np

#: the C library's tanh, element by element (CasADi's): NumPy's float64 tanh runs a SIMD
#: kernel chosen by the CPU (on AVX2 it differs from the C library's in the last bit for a
#: quarter of arguments), so a result would depend on the machine that computed it
tanh = np.vectorize(math.tanh, otypes=[float])

_BINARY = {
    ca.OP_ADD: "({a} + {b})",
    ca.OP_SUB: "({a} - {b})",
    ca.OP_MUL: "({a} * {b})",
    ca.OP_DIV: "({a} / {b})",
    ca.OP_POW: "np.power({a}, {b})",
    ca.OP_CONSTPOW: "np.power({a}, {b})",
    ca.OP_FMIN: "np.minimum({a}, {b})",
    ca.OP_FMAX: "np.maximum({a}, {b})",
    ca.OP_ATAN2: "np.arctan2({a}, {b})",
    ca.OP_HYPOT: "np.hypot({a}, {b})",
    ca.OP_COPYSIGN: "np.copysign({a}, {b})",
    ca.OP_FMOD: "np.fmod({a}, {b})",
    ca.OP_LT: "(({a}) < ({b})) * 1.0",
    ca.OP_LE: "(({a}) <= ({b})) * 1.0",
    ca.OP_EQ: "(({a}) == ({b})) * 1.0",
    ca.OP_NE: "(({a}) != ({b})) * 1.0",
    ca.OP_AND: "np.logical_and({a}, {b}) * 1.0",
    ca.OP_OR: "np.logical_or({a}, {b}) * 1.0",
    ca.OP_IF_ELSE_ZERO: "np.where({a} != 0, {b}, 0.0)",
}
_UNARY = {
    ca.OP_ASSIGN: "{a}",
    ca.OP_NEG: "(-{a})",
    ca.OP_SQ: "({a} * {a})",
    ca.OP_TWICE: "(2.0 * {a})",
    ca.OP_INV: "(1.0 / {a})",
    ca.OP_SQRT: "np.sqrt({a})",
    ca.OP_FABS: "np.abs({a})",
    ca.OP_SIGN: "np.sign({a})",
    ca.OP_FLOOR: "np.floor({a})",
    ca.OP_CEIL: "np.ceil({a})",
    ca.OP_NOT: "(({a}) == 0) * 1.0",
    ca.OP_SIN: "np.sin({a})",
    ca.OP_COS: "np.cos({a})",
    ca.OP_TAN: "np.tan({a})",
    ca.OP_ASIN: "np.arcsin({a})",
    ca.OP_ACOS: "np.arccos({a})",
    ca.OP_ATAN: "np.arctan({a})",
    ca.OP_SINH: "np.sinh({a})",
    ca.OP_COSH: "np.cosh({a})",
    ca.OP_TANH: "tanh({a})",
    ca.OP_EXP: "np.exp({a})",
    ca.OP_LOG: "np.log({a})",
    ca.OP_LOG1P: "np.log1p({a})",
    ca.OP_EXPM1: "np.expm1({a})",
}


#: the names a constant's repr may use (``inf``, ``nan``) in the generated code
_SPECIAL = {"inf": math.inf, "nan": math.nan}


def _statements(fun: ca.Function, binary: dict, unary: dict, read: str, write: str
                ) -> list[str]:
    """One Python statement per SX instruction of ``fun`` (work variables ``w<k>``).

    ``read`` and ``write`` format an input element and an output nonzero from ``i``/``j``
    (the argument) and ``k`` (the element); ``binary`` and ``unary`` map operations to
    expressions of ``a`` and ``b``.

    Raises:
        NotImplementedError: an operation with no entry in ``binary`` or ``unary``.
    """
    out_nz = [fun.sparsity_out(j).find() for j in range(fun.n_out())]
    body: list[str] = []
    for k in range(fun.n_instructions()):
        op = fun.instruction_id(k)
        args = fun.instruction_input(k)
        res = fun.instruction_output(k)
        if op == ca.OP_INPUT:
            body.append(f"w{res[0]} = " + read.format(i=args[0], k=args[1]))
        elif op == ca.OP_OUTPUT:
            body.append(write.format(j=res[0], k=out_nz[res[0]][res[1]]) + f" = w{args[0]}")
        elif op == ca.OP_CONST:
            body.append(f"w{res[0]} = {float(fun.instruction_constant(k))!r}")
        elif op in binary:
            body.append(f"w{res[0]} = " + binary[op].format(a=f"w{args[0]}", b=f"w{args[1]}"))
        elif op in unary:
            body.append(f"w{res[0]} = " + unary[op].format(a=f"w{args[0]}"))
        else:
            raise NotImplementedError(f"{fun.name()}: CasADi operation {op} has no NumPy mapping")
    return body


#: CasADi's operation codes by name (``OP_ERF`` -> ``"erf"``)
_OP_NAMES = {getattr(ca, n): n[3:].lower() for n in dir(ca) if n.startswith("OP_")}


def unsupported_operations(fun: ca.Function) -> list[str]:
    """The names of the operations of ``fun`` that the evaluators here cannot run, sorted.

    ``call``: a call of another Function that does not expand into SX (an interpolant,
    a Callback).
    """
    if not fun.is_a("SXFunction"):
        try:
            fun = fun.expand()
        except RuntimeError:
            return ["call"]
    known = {ca.OP_INPUT, ca.OP_OUTPUT, ca.OP_CONST, *_BINARY, *_UNARY}
    ops = {fun.instruction_id(k) for k in range(fun.n_instructions())} - known
    return sorted(_OP_NAMES.get(op, str(op)) for op in ops)


def supported_operations() -> list[str]:
    """The names of the operations the evaluators here run (sorted)."""
    return sorted(_OP_NAMES.get(op, str(op)) for op in (*_BINARY, *_UNARY))


def compile_numpy(fun: ca.Function) -> Callable[..., list[np.ndarray]]:
    """Generates a NumPy evaluator of an SX function.

    Args:
        fun: CasADi SX function with dense vector inputs and outputs.

    Returns:
        ``call(*args)`` where each arg has shape ``(..., n_in_i)`` (leading batch axes
        broadcast); returns a list of arrays of shape ``(..., n_out_j)``.

    Raises:
        NotImplementedError: the function uses an operation with no NumPy mapping.
    """
    if not fun.is_a("SXFunction"):
        fun = fun.expand()
    n_out = [fun.size1_out(j) * fun.size2_out(j) for j in range(fun.n_out())]
    body = _statements(fun, _BINARY, _UNARY, "a{i}[..., {k}]", "o{j}[..., {k}]")
    n_in = fun.n_in()
    arg_names = ", ".join(f"a{i}" for i in range(n_in))
    lines = [f"def _f({arg_names}):"]
    lines += [f"    a{i} = np.asarray(a{i}, dtype=float)" for i in range(n_in)]
    lines.append("    bshape = a0.shape[:-1]" if n_in else "    bshape = ()")
    for i in range(1, n_in):
        lines.append(f"    if a{i}.shape[:-1] != bshape:")
        lines.append(f"        bshape = np.broadcast_shapes(bshape, a{i}.shape[:-1])")
    lines += [f"    o{j} = np.zeros(bshape + ({n},))" for j, n in enumerate(n_out)]
    lines += ["    " + s for s in body]
    lines.append("    return [" + ", ".join(f"o{j}" for j in range(len(n_out))) + "]")
    namespace: dict = {"np": np, "tanh": tanh, **_SPECIAL}
    exec(compile("\n".join(lines), f"<numpy:{fun.name()}>", "exec"), namespace)  # our own source
    return namespace["_f"]


def _fmin(a: float, b: float) -> float:
    return float(np.minimum(a, b))


def _fmax(a: float, b: float) -> float:
    return float(np.maximum(a, b))


def _sin(a: float) -> float:  # NumPy's loop on one element, as the batch evaluator runs it
    return float(np.sin(np.array((a,)))[0])


def _cos(a: float) -> float:
    return float(np.cos(np.array((a,)))[0])


#: the operations :func:`compile_one` evaluates on Python floats, each as exact as the
#: batch evaluator's: IEEE arithmetic (+, -, *, /, 1/x, x^2, 2x, sqrt, |x|, negation),
#: comparisons and logic giving 0.0 or 1.0 (if_else_zero included), NumPy's own fmin and
#: fmax (on the two floats), sin and cos (on a one-element array) and the C library's
#: tanh (as :data:`tanh`). A function with any other operation gets no single-sample
#: evaluator.
_ONE_BINARY = {
    ca.OP_ADD: "({a} + {b})",
    ca.OP_SUB: "({a} - {b})",
    ca.OP_MUL: "({a} * {b})",
    ca.OP_DIV: "({a} / {b})",
    ca.OP_FMIN: "_fmin({a}, {b})",
    ca.OP_FMAX: "_fmax({a}, {b})",
    ca.OP_LT: "(({a}) < ({b})) * 1.0",
    ca.OP_LE: "(({a}) <= ({b})) * 1.0",
    ca.OP_EQ: "(({a}) == ({b})) * 1.0",
    ca.OP_NE: "(({a}) != ({b})) * 1.0",
    ca.OP_AND: "(1.0 if ({a}) != 0 and ({b}) != 0 else 0.0)",
    ca.OP_OR: "(1.0 if ({a}) != 0 or ({b}) != 0 else 0.0)",
    ca.OP_IF_ELSE_ZERO: "({b} if ({a}) != 0 else 0.0)",
}
_ONE_UNARY = {
    ca.OP_ASSIGN: "{a}",
    ca.OP_NEG: "(-{a})",
    ca.OP_SQ: "({a} * {a})",
    ca.OP_TWICE: "(2.0 * {a})",
    ca.OP_INV: "(1.0 / {a})",
    ca.OP_SQRT: "_sqrt({a})",
    ca.OP_FABS: "abs({a})",
    ca.OP_NOT: "(({a}) == 0) * 1.0",
    ca.OP_TANH: "_tanh({a})",
    ca.OP_SIN: "_sin({a})",
    ca.OP_COS: "_cos({a})",
}


def compile_one(fun: ca.Function, batch: Callable[..., list[np.ndarray]] | None = None
                ) -> Callable[..., list[np.ndarray]] | None:
    """A single-sample evaluator of an SX function on Python floats, or None.

    The same results as :func:`compile_numpy`'s evaluator on a batch of one, bit for bit,
    without NumPy's per-operation overhead. A function with an operation outside the
    exact set above, or without inputs, gets None (use the batch evaluator).

    Args:
        fun: CasADi SX function with dense vector inputs and outputs.
        batch: the batch evaluator of ``fun`` (default: compiled here). It runs instead
            for arguments that are not one sample, where Python floats raise and NumPy
            gives inf or NaN (a division by zero, the square root of a negative number),
            and where an output is not finite (so NumPy's overflow and invalid-value
            warnings are given as before).

    Returns:
        ``call(*args)``, each arg of shape ``(1, n_in_i)`` (another shape: the batch
        evaluator's answer); returns a list of arrays of shape ``(1, n_out_j)``.
    """
    if not fun.is_a("SXFunction"):
        fun = fun.expand()
    if fun.n_in() == 0 or any(
            op not in _ONE_BINARY and op not in _ONE_UNARY and
            op not in (ca.OP_INPUT, ca.OP_OUTPUT, ca.OP_CONST)
            for op in (fun.instruction_id(k) for k in range(fun.n_instructions()))):
        return None
    n_out = [fun.size1_out(j) * fun.size2_out(j) for j in range(fun.n_out())]
    body = _statements(fun, _ONE_BINARY, _ONE_UNARY, "v{i}[{k}]", "o{j}[{k}]")
    n_in = fun.n_in()
    names = ", ".join(f"a{i}" for i in range(n_in))
    outs = [f"o{j}" for j in range(len(n_out))]
    lines = [f"def _one({names}):",
             *[f"    v{i} = _asarray(a{i}, dtype=float)" for i in range(n_in)],
             "    if " + " or ".join(f"v{i}.shape[:-1] != (1,)" for i in range(n_in)) + ":",
             f"        return _batch({names})",
             "    try:",
             *[f"        v{i} = v{i}[0].tolist()" for i in range(n_in)],
             *[f"        o{j} = [0.0] * {n}" for j, n in enumerate(n_out)],
             *["        " + s for s in body],
             "    except (ZeroDivisionError, ValueError, OverflowError):",
             f"        return _batch({names})",
             *([f"    if not all(map(_isfinite, {' + '.join(outs)})):",
                f"        return _batch({names})"] if outs else []),
             "    return [" + ", ".join(f"_array([{o}])" for o in outs) + "]"]
    namespace: dict = {"_fmin": _fmin, "_fmax": _fmax, "_sin": _sin, "_cos": _cos,
                       "_sqrt": math.sqrt, "_tanh": math.tanh, "_isfinite": math.isfinite,
                       "_array": np.array, "_asarray": np.asarray, **_SPECIAL,
                       "_batch": batch if batch is not None else compile_numpy(fun)}
    exec(compile("\n".join(lines), f"<one:{fun.name()}>", "exec"), namespace)  # our own source
    return namespace["_one"]


def compile_evaluator(fun: ca.Function) -> Callable[..., list[np.ndarray]]:
    """The evaluator of ``fun`` for any batch, the same numbers as :func:`compile_numpy`'s.

    A batch of one runs on Python floats (:func:`compile_one`) where ``fun``'s operations
    allow it; every other call is NumPy's.
    """
    batch = compile_numpy(fun)
    return compile_one(fun, batch) or batch
