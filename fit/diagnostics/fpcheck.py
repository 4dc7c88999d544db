"""``texstream fpcheck``: the error of a device's floating-point operations as Warp compiles them.

The dissertation's appendix A (Hillesland 2005) measures the error of a GPU's add, subtract, multiply and
divide in ULPs over Schryer's significand patterns (Table A.1) and reports min / max per operation
(Table A.2), after Paranoia's guard-bit and rounding checks. This stage does the same for add, sub,
mul, div, sqrt, exp, log and pow, one Warp kernel per dtype (``fit/kernels/fparith.py``), on Table A.1's
operands plus random ones:

- **exact references on the host**: ``fractions.Fraction`` for + - * / (exact), an integer square root for
  sqrt (exact, or bracketed within 2^-80 of a ULP), ``mpmath`` at 200 bits for exp, log and pow;
- **error in ULPs** of the result dtype: (computed - exact) / ulp(exact), signed, where ulp(x) is the
  spacing of the dtype's numbers in x's binade (the subnormal spacing below the smallest normal).
  A correctly rounded operation lies in [-0.5, 0.5];
- **rounding**: for + - * / each computed result is compared with the exact result rounded to nearest
  even, toward zero, up and down, and the ties (exact results halfway between two numbers) are counted;
- **Paranoia-style checks** (guard digit, sticky bit, ties to even, x * 1 == x, ...) and **denormal
  checks** (gradual underflow against flush to zero, subnormal operands against denormals-are-zero),
  each a single operation with a known correctly rounded answer.

Exact results outside the dtype's normal range (overflow, or below the smallest normal) are left out of
the ULP statistics and counted; the denormal checks cover that range. Imports only numpy and warp at
module import time (mpmath is imported by :func:`exact_transcendental`).
"""

from __future__ import annotations

import dataclasses
import math
from fractions import Fraction
from typing import Any

import numpy as np

from texstream.core.config import check_config, option
from texstream.core.errors import ConfigError, InputError
from texstream.core.outputs import write_atomic_with, write_json_atomic
from texstream.fit.kernels.fparith import FP_OPS_KERNELS, OPERATIONS

DTYPES = ("float16", "float32", "float64")
SCHRYER_PATTERNS = ("1.00..010..", "1.10..010..", "1.11..101..", "1.00..01..", "1.10..01..", "1.11..10..")
"""Table A.1's significand patterns, in its order"""
ROUNDINGS = ("nearest_even", "toward_zero", "up", "down")


@dataclasses.dataclass(frozen=True)
class FloatFormat:
    """A binary floating-point format: ``precision`` significand bits (with the hidden one), exponents
    of normal numbers from ``emin`` to ``emax``."""

    name: str
    precision: int
    emin: int
    emax: int

    @property
    def numpy(self) -> type:
        return getattr(np, self.name)

    @property
    def min_normal(self) -> Fraction:
        return Fraction(2) ** self.emin

    @property
    def subnormal_spacing(self) -> Fraction:
        return Fraction(2) ** (self.emin - self.precision + 1)

    @property
    def max_finite(self) -> Fraction:
        return (2 - Fraction(2) ** (1 - self.precision)) * Fraction(2) ** self.emax


FORMATS = {"float16": FloatFormat("float16", 11, -14, 15), "float32": FloatFormat("float32", 24, -126, 127),
           "float64": FloatFormat("float64", 53, -1022, 1023)}


@dataclasses.dataclass
class FpcheckConfig:
    """What ``texstream fpcheck`` measures."""

    device: str = option("cpu", "Warp device the operations run on (cpu, cuda:0, ...)")
    dtype: str = option("all", "dtype measured (all: float16, float32 and float64)", choices=("all",) + DTYPES)
    max_significands: int = option(128, "Table A.1 significands per operand, evenly subsampled from every "
                                        "pattern and bit position (float16 has 50, float32 128, float64 302); "
                                        "the pairs are their cross product times 4 relative exponents", min=6)
    random_pairs: int = option(20000, "random operand pairs for + - * / and sqrt", min=0)
    random_transcendental: int = option(4000, "random operands for exp, log and pow (references in mpmath)",
                                        min=0)
    seed: int = option(0, "random seed of the random operands", min=0)


# ---------------------------------------------------------------------------------------------------
# exact arithmetic: binades, ULPs, rounding


def binade(x: Fraction) -> int:
    """floor(log2 |x|) of a non-zero rational."""
    n, d = abs(x.numerator), x.denominator
    e = n.bit_length() - d.bit_length()
    # 2^e <= n/d < 2^(e+1) unless n/d < 2^e
    if (n << max(0, -e)) < (d << max(0, e)):
        e -= 1
    return e


def ulp(x: Fraction, fmt: FloatFormat) -> Fraction:
    """Spacing of ``fmt``'s numbers in the binade of exact value ``x`` (the subnormal spacing below the
    smallest normal, and at 0)."""
    if x == 0:
        return fmt.subnormal_spacing
    return Fraction(2) ** (max(binade(x), fmt.emin) - fmt.precision + 1)


def ulp_error(computed: float, exact: Fraction, fmt: FloatFormat) -> float:
    """Signed error of ``computed`` in ULPs of ``fmt`` at ``exact``: (computed - exact) / ulp(exact)."""
    return float((Fraction(computed) - exact) / ulp(exact, fmt))


def round_exact(x: Fraction, fmt: FloatFormat, mode: str = "nearest_even") -> Fraction:
    """``x`` rounded to ``fmt`` (finite range assumed; subnormals rounded on the subnormal grid) in one of
    :data:`ROUNDINGS`."""
    if x == 0:
        return Fraction(0)
    quantum = ulp(x, fmt)
    scaled = abs(x) / quantum
    low = scaled.numerator // scaled.denominator
    rest = scaled - low
    negative = x < 0
    if rest == 0:
        k = low
    elif mode == "nearest_even":
        k = low + 1 if (rest > Fraction(1, 2) or (rest == Fraction(1, 2) and low % 2 == 1)) else low
    elif mode == "toward_zero":
        k = low
    elif mode == "up":
        k = low if negative else low + 1
    elif mode == "down":
        k = low + 1 if negative else low
    else:
        raise ValueError(f"rounding {mode!r} unknown")
    value = k * quantum
    return -value if negative else value


def is_tie(x: Fraction, fmt: FloatFormat) -> bool:
    """``x`` lies exactly halfway between two neighbours of ``fmt``."""
    if x == 0:
        return False
    scaled = abs(x) / ulp(x, fmt)
    return scaled.denominator == 2


def exact_basic(op: str, a: float, b: float) -> Fraction:
    """Exact result of + - * / on two floats (``Fraction`` holds every binary float exactly)."""
    fa, fb = Fraction(a), Fraction(b)
    if op == "add":
        return fa + fb
    if op == "sub":
        return fa - fb
    if op == "mul":
        return fa * fb
    if op == "div":
        return fa / fb
    raise ValueError(f"operation {op!r} is not basic")


def exact_sqrt(a: float, fmt: FloatFormat) -> Fraction:
    """sqrt(a) exactly when a is a square of a dyadic, else a bracket midpoint within 2^-80 ULP of it
    (integer square root at precision + 80 bits; sqrt of a float is never a rounding tie)."""
    x = Fraction(a)
    if x < 0:
        raise ValueError("sqrt of a negative number")
    if x == 0:
        return Fraction(0)
    # x = num / 2^t; scaled by 4^k it is an integer whose root has at least precision + 80 bits
    t = x.denominator.bit_length() - 1
    k = (t + 1) // 2 + fmt.precision + 80 + max(0, -binade(x))
    scaled = x * Fraction(4) ** k
    n = scaled.numerator // scaled.denominator
    root = math.isqrt(n)
    if root * root == n and scaled.denominator == 1:
        return Fraction(root, 2 ** k)
    return Fraction(2 * root + 1, 2 ** (k + 1))


def exact_transcendental(op: str, a: float, b: float = 0.0) -> Fraction:
    """exp(a), log(a) or pow(a, b) from mpmath at 200 bits, as an exact rational of that value (its
    error, below 2^-190 relative, is far below any ULP measured here)."""
    import mpmath

    with mpmath.workprec(200):
        x = mpmath.mpf(a)
        if op == "exp":
            v = mpmath.exp(x)
        elif op == "log":
            v = mpmath.log(x)
        elif op == "pow":
            v = mpmath.power(x, mpmath.mpf(b))
        else:
            raise ValueError(f"operation {op!r} is not transcendental")
        sign, man, exp, _ = v._mpf_  # mpmath's raw form: (-1)^sign * man * 2^exp (man_exp drops the sign)
    if man == 0:
        return Fraction(0)
    return (-1) ** sign * Fraction(int(man)) * Fraction(2) ** int(exp)


def exact_result(op: str, a: float, b: float, fmt: FloatFormat) -> Fraction:
    if op in ("add", "sub", "mul", "div"):
        return exact_basic(op, a, b)
    if op == "sqrt":
        return exact_sqrt(a, fmt)
    return exact_transcendental(op, a, b)


# ---------------------------------------------------------------------------------------------------
# operands


def schryer_significands(precision: int) -> list[tuple[str, int]]:
    """Table A.1's significands as (pattern, integer significand with ``precision`` bits, leading one
    included), for every bit position, duplicates removed (first pattern kept)."""
    p = precision
    top = 1 << (p - 1)
    out: dict[int, str] = {}
    for j in range(1, p):  # j: position after the binary point, 1..p-1
        cands = [
            (SCHRYER_PATTERNS[0], top | (1 << (p - 1 - j))),
            (SCHRYER_PATTERNS[1], top | (1 << (p - 2)) | (1 << (p - 1 - j)) if j >= 2 else None),
            (SCHRYER_PATTERNS[2], ((1 << p) - 1) & ~(1 << (p - 1 - j))),
            (SCHRYER_PATTERNS[3], top | ((1 << (p - j)) - 1)),
            (SCHRYER_PATTERNS[4], top | (1 << (p - 2)) | ((1 << (p - j)) - 1) if j >= 3 else None),
            (SCHRYER_PATTERNS[5], (1 << p) - (1 << (p - j))),
        ]
        for name, m in cands:
            if m is not None and m not in out:
                out[m] = name
    return sorted(((n, m) for m, n in out.items()), key=lambda t: (SCHRYER_PATTERNS.index(t[0]), t[1]))


def schryer_pairs(fmt: FloatFormat, max_significands: int) -> tuple[np.ndarray, np.ndarray]:
    """Table A.1's operand pairs: a = a significand in [1, 2), b = a significand times 2^r for the
    relative exponents r in {0, -1, -precision/2, -precision}; at most ``max_significands`` significands
    (evenly subsampled) for each operand."""
    sigs = schryer_significands(fmt.precision)
    if len(sigs) > max_significands:
        keep = np.unique(np.linspace(0, len(sigs) - 1, max_significands).round().astype(int))
        sigs = [sigs[i] for i in keep]
    values = np.array([m / 2.0 ** (fmt.precision - 1) for _, m in sigs], np.float64)
    rel = np.array([0, -1, -(fmt.precision // 2), -fmt.precision], np.float64)
    a = np.repeat(values, len(values) * len(rel))
    b = np.tile((values[:, None] * 2.0 ** rel[None, :]).reshape(-1), len(values))
    return a.astype(fmt.numpy), b.astype(fmt.numpy)


def random_floats(rng: np.random.Generator, fmt: FloatFormat, n: int, exponent_span: int,
                  signed: bool = True) -> np.ndarray:
    """Floats with uniformly random significands and exponents in [-exponent_span, exponent_span]."""
    p = fmt.precision
    sig = rng.integers(1 << (p - 1), 1 << p, size=n, dtype=np.int64).astype(np.float64) / 2.0 ** (p - 1)
    e = rng.integers(-exponent_span, exponent_span + 1, size=n)
    v = np.ldexp(sig, e)
    if signed:
        v *= rng.choice([-1.0, 1.0], size=n)
    return v.astype(fmt.numpy)


RANDOM_EXPONENT_SPAN = {"float16": 6, "float32": 40, "float64": 300}
"""random operands of + - * / span 2^-span..2^span: products and quotients stay in the normal range"""


# ---------------------------------------------------------------------------------------------------
# the named single-operation checks


def paranoia_checks(fmt: FloatFormat) -> list[dict]:
    """Paranoia-style guard-digit, sticky-bit and tie checks: single operations whose correctly rounded
    (nearest even) result is known, with what chopping (round toward zero) would give."""
    one = Fraction(1)
    u1 = Fraction(2) ** -fmt.precision  # 1 - (the number below 1)
    u2 = 2 * u1  # ulp of 1
    rows = [
        ("subtraction has a guard digit: 1 - (1 - u1) = u1", "sub", one, one - u1),
        ("x * 1 = x (x = 1 - u1)", "mul", one - u1, one),
        ("x * 1 = x (x = 1 + u2)", "mul", one + u2, one),
        ("x / 1 = x (x = 1 - u1)", "div", one - u1, one),
        ("x / x = 1 (x = 1 - u1)", "div", one - u1, one - u1),
        ("add: tie rounds to even (1 + u2/2)", "add", one, u1),
        ("add: tie rounds to even ((1 + u2) + u2/2)", "add", one + u2, u1),
        ("add: sticky bit (1 + u2/2 (1 + u2))", "add", one, u1 * (one + u2)),
        ("sub: tie rounds to even (1 - u1/2)", "sub", one, u1 / 2),
        ("sub: sticky bit (1 - u1/2 (1 + u2))", "sub", one, u1 / 2 * (one + u2)),
        ("mul: just below a tie ((1 + u2)(1 - u1))", "mul", one + u2, one - u1),
        ("div: 1 / 3", "div", one, Fraction(3)),
        ("div: 2 / 3", "div", Fraction(2), Fraction(3)),
        ("sqrt: exact square (sqrt 9 = 3)", "sqrt", Fraction(9), one),
        ("sqrt: just below one (sqrt(1 - u1))", "sqrt", one - u1, one),
        ("sqrt: just above one (sqrt(1 + u2))", "sqrt", one + u2, one),
    ]
    out = []
    for name, op, a, b in rows:
        exact = exact_result(op, float(a), float(b), fmt)
        out.append({"check": name, "op": op, "a": float(a), "b": float(b),
                    "nearest_even": float(round_exact(exact, fmt, "nearest_even")),
                    "toward_zero": float(round_exact(exact, fmt, "toward_zero"))})
    return out


def denormal_checks(fmt: FloatFormat) -> list[dict]:
    """Gradual underflow and subnormal operands: the correctly rounded result, and what flush-to-zero
    (FTZ, results) or denormals-are-zero (DAZ, operands) would give instead."""
    m = fmt.min_normal
    tiny = fmt.subnormal_spacing
    above = m + ulp(m, fmt)
    rows = [
        ("underflow: min_normal * 1/2 is subnormal", "mul", m, Fraction(1, 2), "ftz", 0.0),
        ("underflow: min_normal / 4 is subnormal", "div", m, Fraction(4), "ftz", 0.0),
        ("x != y implies x - y != 0 (next above min_normal - min_normal)", "sub", above, m, "ftz", 0.0),
        ("subnormal operands: tiny + tiny", "add", tiny, tiny, "daz", 0.0),
        ("subnormal operand: tiny * 2^(p-1) = min_normal", "mul", tiny, Fraction(2) ** (fmt.precision - 1),
         "daz", 0.0),
        ("subnormal operand: sqrt(smallest subnormal)", "sqrt", tiny, Fraction(1), "daz", 0.0),
        ("underflow to zero: smallest subnormal / 2 (tie to even: 0)", "div", tiny, Fraction(2), "none", 0.0),
    ]
    out = []
    for name, op, a, b, flush, flushed in rows:
        exact = exact_result(op, float(a), float(b), fmt)
        out.append({"check": name, "op": op, "a": float(a), "b": float(b),
                    "nearest_even": float(round_exact(exact, fmt, "nearest_even")), "flush": flush,
                    "flushed": flushed})
    return out


# ---------------------------------------------------------------------------------------------------
# running and measuring


def run_operations(a: np.ndarray, b: np.ndarray, dtype: str, device: str) -> np.ndarray:
    """(8, n) results of :data:`fparith.OPERATIONS` on the device, as float64 (exact widening)."""
    import warp as wp

    wdt = {"float16": wp.float16, "float32": wp.float32, "float64": wp.float64}[dtype]
    n = len(a)
    wa = wp.array(np.ascontiguousarray(a), dtype=wdt, device=device)
    wb = wp.array(np.ascontiguousarray(b), dtype=wdt, device=device)
    out = wp.zeros((8, max(n, 1)), dtype=wdt, device=device)
    if n:
        wp.launch(FP_OPS_KERNELS[dtype], dim=n, inputs=[wa, wb], outputs=[out], device=device)
    return out.numpy()[:, :n].astype(np.float64)


def _stats(errors: list[float]) -> dict:
    if not errors:
        return {"n": 0}
    e = np.asarray(errors)
    return {"n": int(e.size), "min_ulp": float(e.min()), "max_ulp": float(e.max()),
            "max_abs_ulp": float(np.abs(e).max()), "mean_abs_ulp": float(np.abs(e).mean())}


def measure_operation(op: str, a: np.ndarray, b: np.ndarray, computed: np.ndarray, fmt: FloatFormat,
                      rounding: bool) -> dict:
    """ULP statistics of one operation over operand pairs (and, with ``rounding``, which rounding each
    result agrees with). Exact results outside the normal range, and pairs outside the domain, are counted
    and left out."""
    errors: list[float] = []
    out_of_range = nonfinite = 0
    agree = dict.fromkeys(ROUNDINGS, 0)
    ties = ties_even = inexact = 0
    for x, y, c in zip(a.tolist(), b.tolist(), computed.tolist()):
        exact = exact_result(op, x, y, fmt)
        if exact != 0 and (abs(exact) < fmt.min_normal or abs(exact) > fmt.max_finite):
            out_of_range += 1
            continue
        if not math.isfinite(c):
            nonfinite += 1
            continue
        errors.append(ulp_error(c, exact, fmt))
        if rounding:
            cf = Fraction(c)
            if round_exact(exact, fmt) != exact:
                inexact += 1
            for mode in ROUNDINGS:
                agree[mode] += cf == round_exact(exact, fmt, mode)
            if is_tie(exact, fmt):
                ties += 1
                ties_even += cf == round_exact(exact, fmt, "nearest_even")
    row = {**_stats(errors), "out_of_range": out_of_range, "nonfinite": nonfinite}
    if rounding:
        row["rounding"] = {"results": len(errors), "inexact": inexact, **agree, "ties": ties,
                           "ties_to_even": ties_even}
    return row


def _operands(fmt: FloatFormat, cfg: FpcheckConfig, rng: np.random.Generator) -> dict[str, dict[str, tuple]]:
    """Per operation, per source ("schryer", "random"): operand arrays (a, b)."""
    sa, sb = schryer_pairs(fmt, cfg.max_significands)
    span = RANDOM_EXPONENT_SPAN[fmt.name]
    ra = random_floats(rng, fmt, cfg.random_pairs, span)
    rb = random_floats(rng, fmt, cfg.random_pairs, span)
    nt = cfg.random_transcendental
    # exp: operands over the range whose result is normal; log: positive, any normal binade
    lo, hi = math.log(float(fmt.min_normal)), math.log(float(fmt.max_finite))
    exp_a = rng.uniform(lo, hi, nt).astype(fmt.numpy)
    log_a = np.abs(random_floats(rng, fmt, nt, fmt.emax - 1))
    # pow: bases around 1 to 2^8 and exponents that keep most results normal
    pow_a = np.exp2(rng.uniform(-8, 8, nt)).astype(fmt.numpy)
    pow_b = rng.uniform(-1, 1, nt) * (min(fmt.emax, 120) / 8.0)
    pow_b = pow_b.astype(fmt.numpy)
    # Table A.1's operands for the unary operations: the significands at every relative exponent
    # (sa, sb hold a in [1, 2) and b = significand * 2^r); exp of them (in [2^-p, 2)), pow(a, +-b)
    unary = np.unique(np.concatenate([sa, sb]))
    tr = unary[:: max(1, len(unary) // max(1, min(len(unary), 2 * cfg.max_significands)))]
    ops = {}
    for op in ("add", "sub", "mul", "div"):
        ops[op] = {"schryer": (sa, sb), "random": (ra, rb)}
    ops["sqrt"] = {"schryer": (unary, unary), "random": (np.abs(ra), rb)}
    ops["exp"] = {"schryer": (tr, tr), "random": (exp_a, exp_a)}
    ops["log"] = {"schryer": (tr, tr), "random": (log_a, log_a)}
    k = min(len(sa), 4 * cfg.max_significands)
    idx = np.linspace(0, len(sa) - 1, k).round().astype(int)
    signs = np.where(np.arange(k) % 2 == 0, 1.0, -1.0).astype(fmt.numpy)
    ops["pow"] = {"schryer": (sa[idx], sb[idx] * signs), "random": (pow_a, pow_b)}
    return ops


def measure_dtype(dtype: str, cfg: FpcheckConfig) -> dict:
    """Every measurement of one dtype on ``cfg.device``: per operation and operand source the ULP
    statistics (and rounding for + - * /), the Paranoia-style checks and the denormal checks."""
    fmt = FORMATS[dtype]
    rng = np.random.default_rng(cfg.seed)
    ops = _operands(fmt, cfg, rng)
    checks = paranoia_checks(fmt)
    dchecks = denormal_checks(fmt)
    # one launch: every operand pair of every operation and check, each row read where it applies
    parts, where = [], {}
    start = 0
    for op, sources in ops.items():
        for src, (a, b) in sources.items():
            parts.append((a, b))
            where[(op, src)] = (start, start + len(a))
            start += len(a)
    check_a = np.array([c["a"] for c in checks + dchecks], fmt.numpy)
    check_b = np.array([c["b"] for c in checks + dchecks], fmt.numpy)
    parts.append((check_a, check_b))
    a_all = np.concatenate([p[0] for p in parts]).astype(fmt.numpy)
    b_all = np.concatenate([p[1] for p in parts]).astype(fmt.numpy)
    results = run_operations(a_all, b_all, dtype, cfg.device)
    row_of = {op: k for k, op in enumerate(OPERATIONS)}

    operations: dict[str, Any] = {}
    for op, sources in ops.items():
        per: dict[str, Any] = {}
        for src in sources:
            s, e = where[(op, src)]
            per[src] = measure_operation(op, a_all[s:e], b_all[s:e], results[row_of[op], s:e], fmt,
                                         rounding=op in ("add", "sub", "mul", "div"))
        both = [per[s] for s in per if per[s]["n"]]
        per["all"] = {"n": sum(r["n"] for r in both),
                      "min_ulp": min(r["min_ulp"] for r in both) if both else None,
                      "max_ulp": max(r["max_ulp"] for r in both) if both else None}
        operations[op] = per

    base = len(a_all) - len(checks) - len(dchecks)
    for k, c in enumerate(checks):
        got = float(results[row_of[c["op"]], base + k])
        c["got"] = got
        c["rounds_to_nearest_even"] = got == c["nearest_even"]
        c["verdict"] = ("nearest even" if got == c["nearest_even"] else
                        "toward zero" if got == c["toward_zero"] else "other")
    for k, c in enumerate(dchecks):
        got = float(results[row_of[c["op"]], base + len(checks) + k])
        c["got"] = got
        c["correct"] = got == c["nearest_even"]
        c["verdict"] = ("correct" if got == c["nearest_even"] else
                        {"ftz": "flushed to zero", "daz": "subnormal operand read as zero"}.get(c["flush"], "other")
                        if got == c["flushed"] else "other")
    results_summary = {
        "gradual_underflow": all(c["correct"] for c in dchecks if c["flush"] == "ftz"),
        "subnormal_operands_honoured": all(c["correct"] for c in dchecks if c["flush"] == "daz"),
    }
    return {"format": dataclasses.asdict(fmt), "operations": operations, "paranoia": checks,
            "denormals": dchecks, "denormal_summary": results_summary}


def device_description(device: str) -> dict:
    import warp as wp

    wp.init()
    try:
        dev = wp.get_device(device)
    except (RuntimeError, ValueError) as e:
        raise ConfigError(f"device {device!r} is not available ({e})",
                          fix="use cpu, or cuda:0 on a machine with a CUDA GPU") from None
    desc = {"device": device, "name": str(getattr(dev, "name", device)), "warp": wp.config.version,
            "fast_math": bool(getattr(wp.config, "fast_math", False))}
    if dev.is_cuda:
        desc["arch"] = f"sm_{dev.arch}"
    else:
        import platform

        desc["cpu"] = platform.processor() or platform.machine()
    return desc


def fpcheck(cfg: FpcheckConfig) -> dict:
    """Measure the dtype(s) of ``cfg`` on ``cfg.device``: a dict with the device's description and, per
    dtype, :func:`measure_dtype`'s results."""
    check_config(cfg)
    desc = device_description(cfg.device)
    dtypes = DTYPES if cfg.dtype == "all" else (cfg.dtype,)
    return {"device": desc, "config": dataclasses.asdict(cfg),
            "dtypes": {dt: measure_dtype(dt, cfg) for dt in dtypes}}


# ---------------------------------------------------------------------------------------------------
# the report


def _span(row: dict) -> str:
    if not row.get("n"):
        return "-"
    return f"[{row['min_ulp']:.3f}, {row['max_ulp']:.3f}]"


def markdown_report(result: dict) -> str:
    """Table A.2's layout (min / max ULP error per operation, one column per dtype), then the rounding
    of + - * /, the Paranoia-style checks and the denormal behaviour."""
    desc = result["device"]
    dts = list(result["dtypes"])
    lines = [f"# Floating-point error on {desc['device']} ({desc['name']})", "",
             f"Warp {desc['warp']}, fast_math {desc['fast_math']}"
             + (f", {desc['arch']}" if "arch" in desc else "") + ". Error in ULPs of the result dtype, "
             "(computed - exact) / ulp(exact); correctly rounded results lie in [-0.5, 0.5].", "",
             "## Error in ULPs (Table A.2 layout): all operands (Table A.1 patterns and random)", "",
             "| operation | " + " | ".join(dts) + " |", "| --- |" + " --- |" * len(dts)]

    for op in OPERATIONS:
        lines.append(f"| {op} | " + " | ".join(_span(result["dtypes"][dt]["operations"][op]["all"])
                                                for dt in dts) + " |")
    lines += ["", "By operand source (Table A.1 patterns / random), cases measured:", "",
              "| operation | " + " | ".join(f"{dt} patterns | {dt} random" for dt in dts) + " |",
              "| --- |" + " --- | --- |" * len(dts)]
    for op in OPERATIONS:
        cells = []
        for dt in dts:
            per = result["dtypes"][dt]["operations"][op]
            cells += [f"{_span(per['schryer'])} ({per['schryer']['n']})", f"{_span(per['random'])} ({per['random']['n']})"]
        lines.append(f"| {op} | " + " | ".join(cells) + " |")
    lines += ["", "## Rounding of + - * /: results agreeing with the exact result rounded each way (ties: exact results halfway between two numbers)", "",
              "| dtype | operation | results (inexact) | nearest even | toward zero | up | down | ties to even |",
              "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for dt in dts:
        for op in ("add", "sub", "mul", "div"):
            rr = [result["dtypes"][dt]["operations"][op][s].get("rounding") for s in ("schryer", "random")]
            rr = [r for r in rr if r]
            tot = {k: sum(r[k] for r in rr) for k in ("results", "inexact", *ROUNDINGS, "ties", "ties_to_even")}
            lines.append(f"| {dt} | {op} | {tot['results']} ({tot['inexact']}) | "
                         + " | ".join(f"{tot[m]}" for m in ROUNDINGS) + f" | {tot['ties_to_even']} of {tot['ties']} |")
    lines += ["", "## Paranoia-style checks", "", "| check | " + " | ".join(dts) + " |",
              "| --- |" + " --- |" * len(dts)]
    first = result["dtypes"][dts[0]]["paranoia"]
    for k, c in enumerate(first):
        lines.append(f"| {c['check']} | " + " | ".join(result["dtypes"][dt]["paranoia"][k]["verdict"] for dt in dts)
                     + " |")
    lines += ["", "## Denormals (subnormal numbers)", "", "| check | " + " | ".join(dts) + " |",
              "| --- |" + " --- |" * len(dts)]
    for k, c in enumerate(result["dtypes"][dts[0]]["denormals"]):
        lines.append(f"| {c['check']} | " + " | ".join(result["dtypes"][dt]["denormals"][k]["verdict"] for dt in dts)
                     + " |")
    lines.append("| gradual underflow (no flush to zero) | " + " | ".join(
        "yes" if result["dtypes"][dt]["denormal_summary"]["gradual_underflow"] else "no" for dt in dts) + " |")
    lines.append("| subnormal operands honoured (no DAZ) | " + " | ".join(
        "yes" if result["dtypes"][dt]["denormal_summary"]["subnormal_operands_honoured"] else "no" for dt in dts)
        + " |")
    return "\n".join(lines) + "\n"


def write_report(result: dict, out_dir) -> tuple:
    """``fpcheck.json`` and ``fpcheck.md`` in ``out_dir``, each written atomically."""
    from pathlib import Path

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", out, "choose another -o folder")
    write_json_atomic(out / "fpcheck.json", result)
    text = markdown_report(result)
    write_atomic_with(out / "fpcheck.md", lambda fh: fh.write(text.encode()))
    return out / "fpcheck.json", out / "fpcheck.md"
