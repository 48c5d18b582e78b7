"""numba with minidem.compile_speed installed: the inliner copies a callee's IR
with one memo for all its blocks, which must be a faithful, independent deep copy, and
the compiler flags give the values numba's own code gives, and a repeated call resolves
from a memo to numba's own signature, and the garbage collector pauses for a compile and
only then (the kernels' machine code is the same with and without any of them; their
results are checked by every physics test)."""

import copy
import gc

import numba
import pytest
from numba.core import compiler, event, inline_closurecall, ir, targetconfig

from minidem import compile_speed
from minidem.engine import simulation  # noqa: F401  (simulation installs it)


def _branchy(x, n):
    total = 0.0
    for k in range(n):
        if x > k:
            total += x * k
        else:
            total -= k
    return total


def test_installed_for_the_engine():
    assert isinstance(inline_closurecall.copy, compile_speed._BlockCopier)
    assert targetconfig.TargetConfig.values is compile_speed.option_values
    assert compile_speed.install()  # idempotent
    assert event._registered["numba:compile"].count(compile_speed._COLLECTOR_PAUSE) == 1


def test_installed_before_the_neighbour_search_compiles():
    # the first compile of a multi-sphere first run is the scene check's neighbour search,
    # before the engine is imported (minidem.engine.warmup): its module installs the repairs
    import subprocess
    import sys

    code = ("import sys\nimport minidem.geometry.neighbours\n"
            "from numba.core import inline_closurecall\nfrom minidem import compile_speed\n"
            "assert 'minidem.engine.simulation' not in sys.modules\n"
            "assert isinstance(inline_closurecall.copy, compile_speed._BlockCopier)\n"
            "assert getattr(compile_speed._COLLECTOR_PAUSE, 'registered', False)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


class _Seen(event.Listener):
    """What the collector's state is while numba compiles (registered after the pause)."""

    def __init__(self):
        self.enabled = []

    def on_start(self, ev):
        self.enabled.append(gc.isenabled())

    def on_end(self, ev):
        pass


@pytest.fixture
def seen():
    listener = _Seen()
    event.register("numba:compile", listener)
    yield listener
    event.unregister("numba:compile", listener)


def test_the_collector_pauses_for_a_compile_and_only_then(seen):
    # repair 4: off from the outermost compile's start (a nested one sees it off too) to
    # its end, on again after; as the program had it: a disabled collector stays disabled,
    # and a compile that fails turns it on again all the same
    inner = numba.njit(lambda x: x * 2.0)

    @numba.njit
    def outer(x):
        return inner(x) + 1.0

    assert gc.isenabled()
    assert outer(1.5) == 4.0
    assert seen.enabled == [False, False] and gc.isenabled()  # outer, then inner inside it

    seen.enabled.clear()
    with pytest.raises(numba.core.errors.TypingError):
        numba.njit(lambda x: x.no_such_attribute)(1.0)
    assert seen.enabled == [False] and gc.isenabled()

    gc.disable()
    try:
        seen.enabled.clear()
        assert numba.njit(lambda x: x - 1.0)(1.0) == 0.0
        assert seen.enabled == [False] and not gc.isenabled()
    finally:
        gc.enable()


def test_an_end_without_its_start_leaves_the_collector_as_it_was():
    # another listener raising on a start stops numba telling the pause of it, and the end
    # still comes: the count must not go below zero (else every later compile would leave
    # the collector off for good)
    pause = compile_speed._COLLECTOR_PAUSE
    assert pause.depth == 0
    pause.on_end(None)
    assert pause.depth == 0 and gc.isenabled()
    assert numba.njit(lambda x: x + 2.0)(1.0) == 3.0
    assert pause.depth == 0 and gc.isenabled()


def _numba_values(config):
    # numba's own TargetConfig.values (numba/core/targetconfig.py, 0.68)
    return {k: getattr(config, k) for k in config.options}


def test_flag_values_are_numbas_key_for_key():
    # the flags numba compiles with: fresh, as a jitted function's (nrt, error model,
    # fastmath, no-cpython wrapper...), and copied; values, key order, hash and equality
    # must be numba's own, or a lookup keyed by flags would miss (a recompile) or, worse,
    # hit another overload
    fresh = compiler.Flags()
    jitted = compiler.Flags()
    jitted.nrt, jitted.no_cpython_wrapper, jitted.error_model = True, True, "numpy"
    jitted.fastmath = True
    jitted.inline = "always"
    copied = jitted.copy()
    for flags in (fresh, jitted, copied):
        assert compile_speed.option_values(flags) == _numba_values(flags)
        assert list(compile_speed.option_values(flags)) == list(_numba_values(flags))
        assert flags.values() == _numba_values(flags)
    assert hash(jitted) == hash(tuple(sorted(_numba_values(jitted)))) and jitted == copied and jitted != fresh
    copied.nrt = False  # set back to its default: equal to a flags object that never set it
    assert copied.values()["nrt"] is False and _numba_values(copied)["nrt"] is False


def test_block_copies_share_one_scope_and_equal_the_original():
    function_ir = compiler.run_frontend(_branchy)
    assert len(function_ir.blocks) > 3
    copier = inline_closurecall.copy
    outer, copier.memos = copier.memos, {}
    try:
        copies = {label: copier.deepcopy(block) for label, block in function_ir.blocks.items()}
    finally:
        copier.memos = outer
    scopes = {id(block.scope) for block in copies.values()}
    assert len(scopes) == 1  # one scope copy, shared as in the original
    (scope,) = {block.scope for block in function_ir.blocks.values()}
    assert next(iter(copies.values())).scope is not scope
    for label, block in function_ir.blocks.items():
        assert str(copies[label]) == str(block)
        assert all(a is not b for a, b in zip(copies[label].body, block.body))
    # an independent copy: renaming in the copy leaves the original as it was
    before = {label: str(block) for label, block in function_ir.blocks.items()}
    for block in copies.values():
        for statement in block.body:
            if isinstance(statement, ir.Assign):
                statement.target = ir.Var(block.scope, statement.target.name + "_renamed", statement.target.loc)
    assert {label: str(block) for label, block in function_ir.blocks.items()} == before
    # outside inline_ir (no memos) it is the plain deep copy
    assert copier.memos is None
    block = next(iter(function_ir.blocks.values()))
    assert str(copier.deepcopy(block)) == str(copy.deepcopy(block))


def test_inlined_function_gives_the_plain_result():
    inner = numba.njit(inline="always")(_branchy)

    @numba.njit
    def outer(x, n):
        return inner(x, n) + inner(x + 1.0, n)

    assert outer(2.5, 7) == _branchy(2.5, 7) + _branchy(3.5, 7)


def test_the_callee_is_copied_once_per_inlining(monkeypatch):
    # numba's inline_ir copies the callee twice, the second copy only to return it, and
    # its callers discard it: with compile_speed that copy is not made. Counted over a
    # compile inlining the callee twice: half the block copies of numba's own way, and
    # the same result.
    copier = inline_closurecall.copy
    plain_deepcopy = copy.deepcopy
    copied = []

    def counting(value, memo=None):
        if isinstance(value, ir.Block):
            copied.append(value)
        return plain_deepcopy(value, memo)

    monkeypatch.setattr(compile_speed.copy, "deepcopy", counting)
    counts = {}
    for skip in (False, True):
        monkeypatch.setattr(type(copier), "skip_discarded_copy", skip)
        copied.clear()
        inner = numba.njit(inline="always")(_branchy)

        @numba.njit
        def outer(x, n):
            return inner(x, n) + inner(x + 1.0, n)

        assert outer(2.5, 7) == _branchy(2.5, 7) + _branchy(3.5, 7)
        counts[skip] = len(copied)
    assert counts[False] > 0 and counts[True] * 2 == counts[False], counts


def _mul_type():
    import operator

    from numba.core.registry import cpu_target

    context = cpu_target.typing_context
    context.refresh()
    return context, context.resolve_value_type(operator.mul)


def test_a_repeated_call_resolves_to_numbas_own_signature_and_implementation():
    # repair 3: the memo gives the signature and implementation key numba's resolution
    # gives (functools.wraps keeps numba's own as __wrapped__), and a hit sets the
    # implementation key again, as a resolution does (the lowering reads the last one set)
    from numba.core.types import functions

    assert functions.BaseFunction.get_call_type._minidem_memo
    plain = functions.BaseFunction.get_call_type.__wrapped__
    context, mul = _mul_type()
    args = (numba.types.float64, numba.types.float64)
    own = plain(mul, context, args, {})
    own_key = mul._impl_keys[own.args]
    first = mul.get_call_type(context, args, {})
    mul._impl_keys[own.args] = "set by another resolution"
    again = mul.get_call_type(context, args, {})
    assert first == own and again is first
    assert mul._impl_keys[own.args] == own_key
    # other argument types, and other compiler flags in force, are other keys
    other = mul.get_call_type(context, (numba.types.int64, numba.types.float64), {})
    assert other == plain(mul, context, (numba.types.int64, numba.types.float64), {})
    flags = compiler.Flags()
    flags.error_model = "numpy"
    with targetconfig.ConfigStack().enter(flags):
        under_flags = mul.get_call_type(context, args, {})
    assert under_flags == own
    keys = [key for key in mul.__dict__["_minidem_calls"] if key[1] == args]
    assert len({key[3] is None for key in keys}) == 2, keys  # one without flags, one with


def test_a_call_that_does_not_type_fails_each_time():
    # a failed resolution is not kept: it raises again, with numba's message
    import pytest

    context, mul = _mul_type()
    args = (numba.types.unicode_type, numba.types.float64)
    for _ in range(2):
        with pytest.raises(numba.core.errors.TypingError, match="No implementation of function"):
            mul.get_call_type(context, args, {})
