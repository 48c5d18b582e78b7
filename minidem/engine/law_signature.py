"""The argument types the kernel passes a law's force function and each kind of part
(what the helper compiles a law for ahead of the kernel: :mod:`minidem.engine.warmup`),
and, when a law breaks the kernel's compilation, why, in terms of the law's own code.
"""

from __future__ import annotations

import inspect
import io
import os
import re
import textwrap
import tokenize

import numba

from minidem.contact import declarations, history as contact_history

def _numba_cause(exc: Exception) -> str:
    """The informative lines of a numba error (it buries the cause among 'During:' lines):
    the message, and where in the law's own code (never the generated kernel's lines)."""
    lines = [line.strip() for line in str(exc).splitlines()]
    message = [line for line in lines if line and not line.startswith(("File ", "During:", "^", "def ", "<source"))
               and "Failed in nopython mode pipeline" not in line]
    places = [line.rstrip(":") for line in lines if line.startswith("File ")
              and "minidem_kernel_" not in line and f"minidem{os.sep}kernel.py" not in line]
    where = f" ({places[-1]})" if places else ""
    return ("; ".join(message[:2]) or lines[0]) + where


def _undefined_name_line(func, exc: Exception) -> str:
    """Where a name numba found undefined is used in ``func`` (its error names no line,
    only the name): ``" (line N uses 'name')"``, or "" when it is not found. Read as
    Python tokens, so a string or a comment that holds the word is not taken for it."""
    found = re.search(r"name '(\w+)' is not defined", str(exc))
    if not found or "line " in str(exc).split(found.group(0), 1)[1][:200]:
        return ""
    try:
        lines, first = inspect.getsourcelines(func)
        tokens = list(tokenize.generate_tokens(io.StringIO(textwrap.dedent("".join(lines))).readline))
    except (OSError, TypeError, tokenize.TokenError, IndentationError):
        return ""
    for token in tokens:
        if token.type == tokenize.NAME and token.string == found.group(1):
            return f" (line {first + token.start[0] - 1} uses '{found.group(1)}')"
    return ""


_ROW, _FLOAT, _VECTOR = (numba.types.Array(numba.types.float64, 1, "C"), numba.types.float64,
                         numba.types.UniTuple(numba.types.float64, 3))
# a contact's history as the kernel hands it over (minidem.contact.history)
_HISTORY = contact_history.contact_history
# the argument types the kernel passes a law's force function (minidem.contact.declarations.FORCE_ARGUMENTS)
_FORCE_SIGNATURE = (_ROW, *(_FLOAT,) * 5, _VECTOR, _VECTOR, _HISTORY)
# a law with a couple (law.couples) also takes the relative rotation over the step, the
# relative spin, the normal and the pair's rolling inertia
_COUPLE_FORCE_SIGNATURE = (*_FORCE_SIGNATURE, _VECTOR, _VECTOR, _VECTOR, _FLOAT)


def force_signature(law: declarations.ContactLaw) -> tuple:
    """The argument types the kernel passes the law's force function."""
    return _COUPLE_FORCE_SIGNATURE if law.couples else _FORCE_SIGNATURE

# the argument types a part's function is called with (minidem.contact.declarations.PART_ARGUMENTS)
# and how many numbers it returns (0: one number)
_PART_SIGNATURES = {
    "normal": ((_ROW, *(_FLOAT,) * 4, _HISTORY), 3),
    "damping": ((_ROW, *(_FLOAT,) * 6), 0),
    "tangential": ((_ROW, *(_FLOAT,) * 7, _VECTOR, _VECTOR, _HISTORY), 3),
    "rolling": ((_ROW, *(_FLOAT,) * 7, _VECTOR, _VECTOR, _HISTORY), 3),
    "twisting": ((_ROW, *(_FLOAT,) * 8, _HISTORY), 0),
}


def _compiled_alone(function, signature, count: int, what: str, shape: str) -> str | None:
    """Why ``function`` does not compile with ``signature`` or does not return ``count``
    numbers (0: one number), naming its file and line; None when it is fine."""
    func = function.py_func
    where = declarations.located(func)
    try:
        function.compile(signature)
    except numba.core.errors.NumbaError as alone:
        return f"its {what} {where} does not compile: {_numba_cause(alone)}{_undefined_name_line(func, alone)}"
    returned = function.overloads[signature].signature.return_type
    number = (numba.types.Float, numba.types.Integer)
    if count == 0:
        if not isinstance(returned, number):
            return f"its {what} {where} must return a number ({shape}), it returns {returned}"
    elif not (isinstance(returned, numba.types.BaseTuple) and len(returned) == count
              and all(isinstance(t, number) for t in returned)):
        if isinstance(returned, numba.types.List):  # return [a, b, ...]: numba's lists are not tuples
            returned = f"a list ({returned}): return a tuple, (a, b, ...)"
        return f"its {what} {where} must return {count} numbers ({shape}), it returns {returned}"
    return None


def _alone_problem(law: declarations.ContactLaw) -> str | None:
    """What is wrong with the law's force function (each part of a combination) compiled
    alone with the engine's argument types, naming the function and its file; None when
    nothing is."""
    shapes = {"normal": "elastic force, stiffness, contact radius", "damping": "the dashpot's force",
              "tangential": "ftx, fty, ftz", "rolling": "the couple mx, my, mz", "twisting": "the couple about n"}
    for part in law.parts:
        signature, count = _PART_SIGNATURES[part.kind]
        why = _compiled_alone(part.function, signature, count, "function", shapes[part.kind])
        if why:
            return f"{part.kind} part '{part.name}': {why}"
    if not law.parts:
        shape = "fn, ftx, fty, ftz" + (", mx, my, mz: a law with couples=True" if law.couples else "")
        return _compiled_alone(law.force, force_signature(law), 7 if law.couples else 4, "force function", shape)
    return None


def law_error(law: declarations.ContactLaw, entry, exc: Exception) -> Exception:
    """The error to raise for ``exc``, raised while the kernel of ``law`` (registered as
    ``entry``) compiled: a LawError naming the law, its plugin and what is wrong with its
    force, for numba's own errors (the force compiled alone with the engine's argument
    types, each part of a combination with its kind's, so that the message names the
    law's or the part's function and file, not the kernel line that called it); for
    another exception (numba raises a bare ValueError
    or TypeError on some return values, e.g. a list where the engine unpacks a tuple) the
    same when compiling the force alone finds the fault, else ``exc`` itself (not the
    law's fault)."""
    from minidem.contact.laws import LawError

    if isinstance(exc, numba.core.errors.NumbaError):
        problem = _alone_problem(law) or f"its force function does not compile in the engine: {_numba_cause(exc)}"
    else:
        try:
            problem = _alone_problem(law)
        except Exception:  # noqa: BLE001 - the original error is the one to report
            problem = None
        if problem is None:
            return exc
    return LawError(f"law '{law.name}' from plugin '{entry.plugin}' ({entry.distribution}): {problem}")
