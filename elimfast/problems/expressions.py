"""Expressions are data: a whitelist parser over Python's ``ast`` for config strings.

A config may write a Hamiltonian, an invariant, a parameter or a number as text. The text
is parsed by ``ast.parse(mode="eval")`` and every node is checked against a whitelist
before anything is built from it; nothing is ever evaluated by Python (no ``eval``, no
``sympify`` of raw text, no ``getattr`` on names the user chose). What is allowed:

- numbers (``2``, ``0.5``, ``1e-15``), the names declared by the problem (coordinates,
  parameters) and the constants ``pi`` and ``e``;
- ``+ - * / **``, unary ``-`` and ``+``, parentheses;
- calls, with positional arguments only, to ``sqrt exp log sin cos tan sinh cosh tanh
  arcsin asin arccos acos arctan atan atan2 abs``. Functions with a kink or a jump (``min``,
  ``max``, ``sign``, ``floor``, ...) are refused with a smooth combination to write instead:
  the gradients (and Hessians) are generated from the expressions.

Everything else (attributes, subscripts, lambdas, comprehensions, strings, keyword
arguments, comparisons, unknown names, dunder names, ...) raises ``ExpressionError``
naming the offending token. So does any non-ASCII character: Python's parser
NFKC-normalises identifiers, so ``q1`` or ``sqrt`` typed in fullwidth letters and digits
(U+FF51 U+FF11, ...) would silently become ``q1`` or ``sqrt``; names (``check_name``)
must be ASCII for the same reason. Sizes are bounded (``MAX_LENGTH`` characters,
``MAX_NODES`` nodes, ``MAX_DEPTH`` nesting, constant exponents up to ``MAX_EXPONENT``),
so no input can make the parser or sympy run away (a problem's total size and the
size of its derivatives are bounded in ``symbolic.py``).

The same validated tree serves three consumers:
- ``to_sympy``: a sympy expression built node by node (exact integers and rationals,
  floats kept as the exact binary double) for differentiation and code generation;
- ``evaluate``: a float in IEEE double arithmetic, as Python's ``math`` would compute
  it (``"pi/30"`` gives exactly ``math.pi / 30``), for numeric config values;
- ``canonical``: a whitespace-independent key (``ast.dump``) for caches.
sympy is imported only by ``to_sympy``, so evaluating numbers stays cheap.
"""
from __future__ import annotations

import ast
import keyword
import math
import re
import unicodedata
import warnings
from typing import Mapping

from ..errors import ElimfastError, closest

MAX_LENGTH = 20_000          # characters in one expression
MAX_NODES = 5_000            # AST nodes in one expression
MAX_DEPTH = 60               # nesting depth of the AST
MAX_EXPONENT = 64            # |constant exponent| in a ** b
MAX_CONSTANT_BITS = 1_100    # exact integers/rationals built while folding constants (~1e330)
MAX_MAGNITUDE = 1e300        # any constant, literal or folded
EXACT_INTEGER_LIMIT = 2 ** 53  # larger integer literals become floats

# name -> number of arguments; the aliases arcsin/asin etc. are the same function.
FUNCTIONS = {
    "sqrt": 1, "exp": 1, "log": 1, "sin": 1, "cos": 1, "tan": 1, "sinh": 1, "cosh": 1, "tanh": 1,
    "arcsin": 1, "asin": 1, "arccos": 1, "acos": 1, "arctan": 1, "atan": 1, "atan2": 2, "abs": 1,
}
CONSTANTS = {"pi": math.pi, "e": math.e}
# Functions with a kink or a jump, which are not offered: every expression must be smooth, since
# elimfast generates its gradient (and Hessian) and steps with them. Refused with what to write
# instead: "did you mean 'sin'?" for min (a user trial's time scale, the smaller of two distances'
# powers) helped nobody. For two positive a, b: 1/(1/a + 1/b) is between min/2 and min,
# (a**-8 + b**-8)**(-1/8) between 0.917 min and min; max alike.
_SMOOTH_MIN = ("for the smaller of two positive values a, b write a smooth combination such as 1/(1/a + 1/b) "
               "(min/2 to min) or (a**-8 + b**-8)**(-1/8) (0.917 min to min)")
_SMOOTH_MAX = ("for the larger of two positive values a, b write a smooth combination such as a + b (max to 2 max) "
               "or (a**8 + b**8)**(1/8) (max to 1.091 max)")
NOT_SMOOTH = {
    **dict.fromkeys(("min", "Min", "amin", "minimum", "fmin"), ("has a kink where its arguments cross", _SMOOTH_MIN)),
    **dict.fromkeys(("max", "Max", "amax", "maximum", "fmax"), ("has a kink where its arguments cross", _SMOOTH_MAX)),
    **dict.fromkeys(("sign", "heaviside", "Heaviside", "step"),
                    ("jumps at 0", "for a smooth switch of width d write tanh(x/d)")),
    **dict.fromkeys(("floor", "ceil", "round", "trunc", "fmod", "mod", "clip", "where", "piecewise",
                     "Piecewise"), ("is not smooth", "write the expression without it")),
}
# Functions spelt out with the allowed ones (a close name, log for log10, would be wrong).
WRITTEN_OUT = {"pow": "a**b", "power": "a**b", "hypot": "sqrt(a**2 + b**2)", "log10": "log(x)/log(10)",
               "log2": "log(x)/log(2)", "exp2": "2**x", "square": "x**2", "arctan2": "atan2(y, x)"}
RESERVED_NAMES = frozenset(FUNCTIONS) | frozenset(CONSTANTS)

_MATH = {
    "sqrt": math.sqrt, "exp": math.exp, "log": math.log, "sin": math.sin, "cos": math.cos,
    "tan": math.tan, "sinh": math.sinh, "cosh": math.cosh, "tanh": math.tanh,
    "arcsin": math.asin, "asin": math.asin, "arccos": math.acos, "acos": math.acos,
    "arctan": math.atan, "atan": math.atan, "atan2": math.atan2, "abs": abs,
}
_BINARY_SYMBOLS = {ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.Div: "/", ast.Pow: "**"}
_FORBIDDEN_OPERATORS = {
    ast.BitXor: "'^' (write powers as '**')", ast.FloorDiv: "'//'", ast.Mod: "'%'",
    ast.MatMult: "'@'", ast.LShift: "'<<'", ast.RShift: "'>>'", ast.BitOr: "'|'", ast.BitAnd: "'&'",
}
_NODE_WORDS = {
    ast.Attribute: "attribute access", ast.Subscript: "indexing", ast.Lambda: "a lambda",
    ast.ListComp: "a comprehension", ast.SetComp: "a comprehension", ast.DictComp: "a comprehension",
    ast.GeneratorExp: "a generator expression", ast.Compare: "a comparison", ast.BoolOp: "'and'/'or'",
    ast.IfExp: "a conditional expression", ast.NamedExpr: "an assignment ':='", ast.Starred: "'*' unpacking",
    ast.List: "a list", ast.Tuple: "a tuple", ast.Dict: "a dict", ast.Set: "a set",
    ast.JoinedStr: "an f-string", ast.Await: "'await'", ast.Yield: "'yield'", ast.YieldFrom: "'yield'",
    ast.Slice: "a slice",
}
_IDENTIFIER = re.compile(r"[A-Za-z][A-Za-z0-9_]*\Z")


class ProblemDefinitionError(ElimfastError, ValueError):
    """A user-defined problem that cannot be built. ``key``: where in the problem's
    description the fault is (e.g. ``"invariants.lrl_y"``), for config messages; or None."""

    def __init__(self, message: str, key: str | None = None):
        super().__init__(message)
        self.key = key


class ExpressionError(ProblemDefinitionError):
    """An expression string that is not allowed or not valid. ``token`` is the offending piece."""

    def __init__(self, message: str, token: str | None = None, key: str | None = None, detail: str | None = None):
        super().__init__(message, key=key)
        self.token = token
        self.detail = detail or message   # what is wrong, without the "hamiltonian '...': " prefix


def _short(text: str, limit: int = 60) -> str:
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _segment(text: str, node: ast.AST) -> str:
    try:
        segment = ast.get_source_segment(text, node)
    except Exception:  # positions can be missing on synthetic nodes
        segment = None
    return _short(segment if segment else type(node).__name__)


def non_ascii(text: str) -> str | None:
    """The first non-ASCII character of text, described (``'１' (U+FF11 FULLWIDTH DIGIT ONE)``), or None."""
    for char in text:
        if ord(char) > 127:
            return f"{char!r} (U+{ord(char):04X} {unicodedata.name(char, 'unnamed')})"
    return None


def check_name(name, what: str = "name") -> str:
    """A coordinate, parameter or invariant name: an ASCII identifier, not a keyword,
    not a function or constant of the expression language, no leading underscore."""
    if not isinstance(name, str):
        raise ExpressionError(f"{what} must be a string, got {name!r}", token=repr(name))
    character = non_ascii(name)
    if character:
        raise ExpressionError(f"{what} {name!r} contains the non-ASCII character {character}; use ASCII "
                              "letters, digits and '_' (Python's parser would read a fullwidth name as its ASCII "
                              "twin)", token=name)
    if not _IDENTIFIER.match(name) or keyword.iskeyword(name):
        raise ExpressionError(f"{what} {name!r} is not a valid name: use letters, digits and '_', "
                              "starting with a letter", token=name)
    if name in RESERVED_NAMES:
        raise ExpressionError(f"{what} {name!r} is reserved for the function or constant of that name; "
                              "choose another name", token=name)
    return name


def did_you_mean(word: str, options) -> str:
    """A hint such as ``; did you mean 'q1'?`` for the closest option (errors.closest), or an empty string."""
    close = closest(word, options, cutoff=0.5)
    return f"; did you mean {close!r}?" if close is not None else ""


def not_allowed_function(name: str) -> str:
    """Why a function name is refused and what to write instead: a smooth combination for one
    with a kink or a jump (NOT_SMOOTH), the spelt-out form for WRITTEN_OUT, else the closest
    allowed function; then the allowed ones."""
    allowed = f"(allowed: {', '.join(FUNCTIONS)})"
    if name in NOT_SMOOTH:
        flaw, instead = NOT_SMOOTH[name]
        return (f"{name!r} is not an allowed function: expressions must be smooth, since their gradients are "
                f"generated from them, and {name} {flaw}; {instead} {allowed}")
    if name in WRITTEN_OUT:
        return f"{name!r} is not an allowed function: write {WRITTEN_OUT[name]} {allowed}"
    return f"{name!r} is not an allowed function{did_you_mean(name, FUNCTIONS)} {allowed}"


def parse(text, names=(), what: str = "expression") -> ast.Expression:
    """Parse and validate ``text``; return the checked tree. ``names``: the declared names."""
    if isinstance(text, bool) or not isinstance(text, (str, int, float)):
        raise ExpressionError(f"{what} must be a string or a number, got {type(text).__name__} {_short(repr(text))}")
    if not isinstance(text, str):
        text = repr(text)
    if len(text) > MAX_LENGTH:
        raise ExpressionError(f"{what} is too long ({len(text)} characters, at most {MAX_LENGTH})")
    if not text.strip():
        raise ExpressionError(f"{what} is empty")
    character = non_ascii(text)
    if character:
        detail = (f"contains the non-ASCII character {character}; write names, numbers and operators in ASCII "
                  "(Python's parser would silently read a fullwidth letter or digit as its ASCII twin)")
        raise ExpressionError(f"{what} {_short(text)!r} {detail}", token=character, detail=detail)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # e.g. SyntaxWarning: invalid decimal literal
            tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError as err:
        near = f" near {_short(err.text.strip(), 30)!r}" if err.text and err.text.strip() else ""
        detail = f"not a valid expression ({_short(err.msg, 80)}{near})"
        raise ExpressionError(f"{what} {_short(text)!r} is {detail}", detail=detail) from None
    except (ValueError, RecursionError, MemoryError, OverflowError) as err:
        # null bytes, integer literals of more than 4300 digits, pathological nesting
        detail = f"cannot be parsed ({type(err).__name__}: {_short(str(err))})"
        raise ExpressionError(f"{what} {_short(text)!r} {detail}", detail=detail) from None
    _Validator(text.strip(), frozenset(names), what).check(tree)
    return tree


class _Validator:
    def __init__(self, text: str, names: frozenset, what: str):
        self.text, self.names, self.what = text, names, what
        self.count = 0

    def fail(self, node, message: str):
        token = _segment(self.text, node)
        raise ExpressionError(f"{self.what} {_short(self.text)!r}: {message}", token=token, detail=message)

    def check(self, tree: ast.Expression) -> None:
        # Iterative depth-first walk: a recursive one could itself hit the recursion limit.
        stack = [(tree.body, 1)]
        while stack:
            node, depth = stack.pop()
            self.count += 1
            if self.count > MAX_NODES:
                self.fail(node, f"too large (more than {MAX_NODES} terms)")
            if depth > MAX_DEPTH:
                self.fail(node, f"nested too deeply (more than {MAX_DEPTH} levels)")
            children = self.children(node)
            if isinstance(node, ast.BinOp) and _chain_class(node.left) == _chain_class(node) is not None:
                # a + b + c parses as ((a + b) + c): a long sum or product is flat, not nested
                stack.append((children[0], depth))
                children = children[1:]
            stack.extend((child, depth + 1) for child in children)

    def children(self, node) -> list:
        if isinstance(node, ast.BinOp):
            if type(node.op) not in _BINARY_SYMBOLS:
                word = _FORBIDDEN_OPERATORS.get(type(node.op), type(node.op).__name__)
                self.fail(node, f"operator {word} is not allowed in {_short(_segment(self.text, node))!r}; "
                                "allowed: + - * / **")
            return [node.left, node.right]
        if isinstance(node, ast.UnaryOp):
            if not isinstance(node.op, (ast.USub, ast.UAdd)):
                self.fail(node, f"{_segment(self.text, node)!r}: only unary '-' and '+' are allowed")
            return [node.operand]
        if isinstance(node, ast.Constant):
            value = node.value
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                self.fail(node, f"{_segment(self.text, node)!r} is not a number: only numbers, names and "
                                "arithmetic are allowed")
            try:
                magnitude = abs(float(value))
            except OverflowError:
                magnitude = math.inf
            if not magnitude <= MAX_MAGNITUDE:
                self.fail(node, f"number {_segment(self.text, node)!r} is too large (at most {MAX_MAGNITUDE:g})")
            return []
        if isinstance(node, ast.Name):
            name = node.id
            if name in self.names or name in CONSTANTS:
                return []
            if name in FUNCTIONS:
                self.fail(node, f"{name!r} is a function: call it as {name}(...)")
            if name in NOT_SMOOTH or name in WRITTEN_OUT:
                self.fail(node, not_allowed_function(name))
            if name in ("t", "time"):   # a user trial's cos(t) in H was told only "unknown name 't'"
                self.fail(node, f"unknown name {name!r}: expressions depend on the state (q, p) and parameters, "
                                "not on the time (elimfast integrates autonomous Hamiltonians); for an H that "
                                "depends on t, make t a coordinate with a conjugate momentum E and add E to H "
                                "(the extended phase space)")
            known = sorted(self.names) + sorted(CONSTANTS)
            hint = did_you_mean(name, known)
            listed = ", ".join(known)
            self.fail(node, f"unknown name {name!r}{hint} (known: {listed})")
        if isinstance(node, ast.Call):
            func = node.func
            if not isinstance(func, ast.Name):
                self.fail(func, f"{_segment(self.text, func)!r} cannot be called: only the functions "
                                f"{', '.join(FUNCTIONS)}")
            if func.id not in FUNCTIONS:
                self.fail(func, not_allowed_function(func.id))
            if node.keywords:
                self.fail(node, f"{func.id}(...): keyword arguments are not allowed")
            arity = FUNCTIONS[func.id]
            if any(isinstance(a, ast.Starred) for a in node.args):
                self.fail(node, f"{func.id}(...): '*' unpacking is not allowed")
            if len(node.args) != arity:
                self.fail(node, f"{func.id} takes {arity} argument{'s' if arity > 1 else ''}, "
                                f"got {len(node.args)} in {_segment(self.text, node)!r}")
            return list(node.args)
        word = _NODE_WORDS.get(type(node), type(node).__name__)
        self.fail(node, f"{word} ({_segment(self.text, node)!r}) is not allowed: only numbers, declared "
                        "names, + - * / **, parentheses and the functions " + ", ".join(FUNCTIONS))


def _chain_class(node):
    """'sum' for + and -, 'product' for * and /, None otherwise (** and the rest nest)."""
    if isinstance(node, ast.BinOp):
        if isinstance(node.op, (ast.Add, ast.Sub)):
            return "sum"
        if isinstance(node.op, (ast.Mult, ast.Div)):
            return "product"
    return None


def _unchain(node):
    """The operands of a left-associated chain a op b op c ...: (first, [(op, operand), ...])."""
    kind = _chain_class(node)
    rest = []
    while _chain_class(node) == kind:
        rest.append((type(node.op), node.right))
        node = node.left
    rest.reverse()
    return node, rest


# Allowed functions with a kink: abs is smooth wherever its argument keeps its sign (abs(x2 - x1) of
# ordered particles), which elimfast cannot tell ahead; where it passes through 0 no quadrature
# follows the kink, and H is lost there whatever k and h (a user trial was told to raise k).
KINKED = ("abs",)


def kinked_functions(tree: ast.Expression) -> tuple[str, ...]:
    """The functions of KINKED that a validated tree calls, in KINKED's order."""
    called = {node.func.id for node in ast.walk(tree) if isinstance(node, ast.Call) and isinstance(node.func, ast.Name)}
    return tuple(name for name in KINKED if name in called)


def kink_note(kinks) -> str:
    """What a run's H note and `check` say of H's kinked functions ('' for none)."""
    if not kinks:
        return ""
    return (f"H uses {' and '.join(kinks)}: where its argument passes through 0 along the orbit, no quadrature keeps "
            "H across that kink, whatever k and h (write a smooth form, e.g. sqrt(x**2 + d**2) for abs(x))")


def polynomial_degree(tree: ast.Expression, variables) -> int | None:
    """An upper bound of the total degree of a validated tree as a polynomial in ``variables``
    (names), or None when it is not visibly one (a function or a quotient of them, a power
    other than a literal whole number): HBVM(k,s) integrates a polynomial H of degree
    <= 2k/s exactly (docs/methods.md). Never below the true degree; above it only where
    terms cancel ((q + 1)**2 - q**2 counts 2), which claims exactness less often, never wrongly."""
    variables = frozenset(variables)

    def literal_exponent(node) -> int | None:
        if isinstance(node, ast.Constant) and isinstance(node.value, int) and not isinstance(node.value, bool):
            return node.value if 0 <= node.value <= 64 else None
        if isinstance(node, ast.Constant) and isinstance(node.value, float) and node.value.is_integer():
            return int(node.value) if 0 <= node.value <= 64 else None
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.UAdd):
            return literal_exponent(node.operand)
        return None

    def degree(node) -> int | None:
        if isinstance(node, ast.Constant):
            return 0
        if isinstance(node, ast.Name):
            return 1 if node.id in variables else 0
        if isinstance(node, ast.UnaryOp):
            return degree(node.operand)
        if _chain_class(node) is not None:   # a whole chain at once: long sums nest deeply
            first, rest = _unchain(node)
            total = degree(first)
            for op, operand in rest:
                part = degree(operand)
                if total is None or part is None or (op is ast.Div and part != 0):
                    return None
                total = max(total, part) if op in (ast.Add, ast.Sub) else total + part
            return total
        if isinstance(node, ast.BinOp):   # a power
            base, exponent = degree(node.left), degree(node.right)
            if base == 0 and exponent == 0:
                return 0
            power = literal_exponent(node.right)
            return None if base is None or power is None else base * power
        if isinstance(node, ast.Call):
            return 0 if all(degree(argument) == 0 for argument in node.args) else None
        return None

    return degree(tree.body if isinstance(tree, ast.Expression) else tree)


def node_count(tree: ast.Expression) -> int:
    """The number of expression nodes (``ast.expr``) of a tree: a problem's total is bounded by
    ``symbolic.MAX_TOTAL_NODES``."""
    return sum(1 for node in ast.walk(tree) if isinstance(node, ast.expr))


def canonical(tree: ast.Expression) -> str:
    """A key of the validated expression, independent of spacing and redundant parentheses."""
    return ast.dump(tree, annotate_fields=False, include_attributes=False)


# --- floats ------------------------------------------------------------------------------

def evaluate(tree: ast.Expression, values: Mapping[str, float] | None = None, what: str = "expression",
             text: str = "") -> float:
    """The value of a validated tree in double-precision arithmetic (as Python's math computes it)."""
    values = dict(values or {})

    def fail(message):
        raise ExpressionError(f"{what} {_short(text)!r}: {message}" if text else f"{what}: {message}",
                              detail=message)

    def value(node):
        if isinstance(node, ast.Constant):
            return float(node.value)
        if isinstance(node, ast.Name):
            if node.id in values:
                return float(values[node.id])
            if node.id in CONSTANTS:
                return CONSTANTS[node.id]
            fail(f"{node.id!r} has no numeric value here")
        if isinstance(node, ast.UnaryOp):
            operand = value(node.operand)
            return -operand if isinstance(node.op, ast.USub) else operand
        if _chain_class(node) is not None:
            first, rest = _unchain(node)
            result = value(first)
            for op, operand in rest:   # left to right, as Python evaluates the chain
                b = value(operand)
                if op is ast.Add:
                    result = result + b
                elif op is ast.Sub:
                    result = result - b
                elif op is ast.Mult:
                    result = result * b
                else:
                    if b == 0.0:
                        fail("division by zero")
                    result = result / b
            return result
        if isinstance(node, ast.BinOp):
            a, b = value(node.left), value(node.right)
            result = a ** b
            if isinstance(result, complex):
                fail(f"({a!r})**({b!r}) is not a real number")
            return result
        if isinstance(node, ast.Call):
            args = [value(a) for a in node.args]
            return _MATH[node.func.id](*args)
        fail(f"cannot evaluate {type(node).__name__}")  # unreachable for a validated tree

    try:
        result = value(tree.body)
    except ExpressionError:
        raise
    except ZeroDivisionError:
        fail("division by zero")
    except OverflowError:
        fail("the value overflows a double")
    except ValueError as err:  # math domain errors
        fail(f"not defined ({err})")
    if not math.isfinite(result):
        fail(f"the value is not finite ({result})")
    return float(result)


def evaluate_number(value, names: Mapping[str, float] | None = None, what: str = "value") -> float:
    """A config number: an int or float as is, or a string such as ``"pi/30"``, ``"1e-15"``,
    ``"2*pi*10"``; ``names`` may supply values of names (e.g. parameters). Returns a finite float."""
    if isinstance(value, bool):
        raise ExpressionError(f"{what} must be a number, got {value!r}")
    if isinstance(value, (int, float)):
        try:
            result = float(value)
        except OverflowError:
            raise ExpressionError(f"{what} is too large for a double") from None
        if not math.isfinite(result):
            raise ExpressionError(f"{what} must be finite, got {value!r}")
        return result
    if not isinstance(value, str):
        got = "an empty value (null)" if value is None else type(value).__name__   # key: or --set key=
        raise ExpressionError(f"{what} must be a number or an arithmetic expression such as 'pi/30', got {got}")
    tree = parse(value, names=tuple(names or ()), what=what)
    return evaluate(tree, names, what=what, text=value)


# --- sympy -------------------------------------------------------------------------------

def to_sympy(tree: ast.Expression, symbols: Mapping, what: str = "expression", text: str = ""):
    """A sympy expression built node by node from a validated tree.

    ``symbols`` maps every declared name to its sympy Symbol. Integer literals up to 2^53
    stay exact (so ``p**2/2`` differentiates to ``p``), floats are the exact doubles.
    Rejects results that are undefined (``1/0``), complex (``sqrt(-1)``) or too large.
    """
    import sympy

    functions = {
        "sqrt": sympy.sqrt, "exp": sympy.exp, "log": sympy.log, "sin": sympy.sin, "cos": sympy.cos,
        "tan": sympy.tan, "sinh": sympy.sinh, "cosh": sympy.cosh, "tanh": sympy.tanh,
        "arcsin": sympy.asin, "asin": sympy.asin, "arccos": sympy.acos, "acos": sympy.acos,
        "arctan": sympy.atan, "atan": sympy.atan, "atan2": sympy.atan2, "abs": sympy.Abs,
    }
    constants = {"pi": sympy.pi, "e": sympy.E}
    label = f"{what} {_short(text)!r}" if text else what

    def fail(message):
        raise ExpressionError(f"{label}: {message}", detail=message)

    undefined = (sympy.zoo, sympy.nan, sympy.oo, -sympy.oo)

    def check_constant(result, node):
        if result in undefined:
            fail(f"{_segment(text, node) if text else 'a term'} is undefined (division by zero, log(0)?)")
        if result.is_Number:
            if result is sympy.nan or result.is_infinite or result is sympy.zoo:
                fail(f"{_segment(text, node) if text else 'a term'} is undefined (division by zero?)")
            if result.is_Rational and max(abs(result.p).bit_length(), result.q.bit_length()) > MAX_CONSTANT_BITS:
                fail(f"the constant {_segment(text, node) if text else ''} is too large")
            if result.is_Float and not abs(float(result)) <= MAX_MAGNITUDE:
                fail(f"the constant {_segment(text, node) if text else ''} is too large")
        return result

    def power(base, exponent, node):
        if exponent.is_Number:
            if not abs(float(exponent)) <= MAX_EXPONENT:
                fail(f"exponent {exponent} in {_segment(text, node) if text else 'a power'} is too large "
                     f"(at most {MAX_EXPONENT})")
            if base.is_Rational:
                bits = max(abs(base.p).bit_length(), base.q.bit_length()) * abs(float(exponent))
                if bits > MAX_CONSTANT_BITS:
                    fail(f"the constant {_segment(text, node) if text else ''} is too large")
            if base.is_zero and exponent.is_negative:
                fail(f"{_segment(text, node) if text else 'a power'} divides by zero")
        return base ** exponent

    def build(node):
        if isinstance(node, ast.Constant):
            v = node.value
            if isinstance(v, int) and abs(v) <= EXACT_INTEGER_LIMIT:
                return sympy.Integer(v)
            return sympy.Float(float(v))
        if isinstance(node, ast.Name):
            if node.id in symbols:
                return symbols[node.id]
            return constants[node.id]
        if isinstance(node, ast.UnaryOp):
            operand = build(node.operand)
            return check_constant(-operand, node) if isinstance(node.op, ast.USub) else operand
        if _chain_class(node) is not None:
            # One Add or Mul for the whole chain: pairwise construction would be quadratic.
            first, rest = _unchain(node)
            terms = [build(first)]
            for op, operand in rest:
                b = build(operand)
                if op is ast.Sub:
                    b = -b
                elif op is ast.Div:
                    if b.is_zero:
                        fail(f"division by zero in {_segment(text, node) if text else 'a quotient'}")
                    b = 1 / b
                terms.append(b)
            return check_constant(sympy.Add(*terms) if _chain_class(node) == "sum" else sympy.Mul(*terms), node)
        if isinstance(node, ast.BinOp):
            base, exponent = build(node.left), build(node.right)
            if not (base.free_symbols or exponent.free_symbols) and not (base.is_Rational and exponent.is_Integer):
                return fold(node)
            return check_constant(power(base, exponent, node), node)
        args = [build(a) for a in node.args]
        if not any(a.free_symbols for a in args):
            return fold(node)
        return check_constant(functions[node.func.id](*args), node)

    def fold(node):
        # A constant call or non-integer power: its double value, as the compiled code would
        # compute it. sympy never sees e.g. acos(100) (complex) or atan2 of such constants,
        # on which its simplification can take very long.
        value = evaluate(ast.Expression(body=node), {}, what=what, text=text)
        return sympy.Float(value)

    # The validated tree nests at most MAX_DEPTH deep (chains are folded in a loop): bounded recursion.
    try:
        expr = build(tree.body)
    except (TypeError, ValueError, ArithmeticError) as err:
        if isinstance(err, ExpressionError):
            raise
        # sympy refusing a combination of constants, e.g. atan2(0, nan)
        fail(f"cannot be evaluated symbolically ({type(err).__name__}: {_short(str(err))})")
    if expr.has(sympy.zoo, sympy.nan, sympy.oo, -sympy.oo):
        fail("the expression is undefined somewhere in its constants (division by zero, log(0)?)")
    if expr.has(sympy.I):
        fail("the expression is complex (e.g. sqrt or log of a negative constant); it must be real")
    return expr
