"""Four repairs of numba's compile speed, installed when the engine or the neighbour search
is imported, before either compiles anything (the same machine code either way; what each
saves is measured below).

1. Its inlining of ``inline="always"`` functions copies each callee's IR once.

Why: the kernel (``minidem.engine.kernel``) is one function per law and scene shape, built
by numba inlining its per-step functions and helpers into ``advance``. Before inlining a
callee, numba (``numba.core.inline_closurecall.InlineWorker.inline_ir``, up to at least
0.68) deep-copies the callee's IR twice, one ``copy.deepcopy`` per basic block. Every
variable refers to the function's scope, and the scope holds every variable, so each
block's copy copies the whole scope again: the cost grows with blocks x variables. For
the force pass (~55 blocks, ~1,300 statements) that was a third of the CPU time of a
first run of scenarios/oblique.toml (3.9 of 10.9 s, measured with a timer around
``copy.deepcopy``; numba issues #8989 and #9204 describe the same cost).

The fix copies the blocks of one IR with one shared memo, as ``copy.deepcopy`` of the
whole block dictionary would: the scope and the variables are copied once and shared by
the copied blocks, exactly as they are shared by the original ones. The IR numba then
builds is the same, statement for statement, and so is the machine code: the assembly of
the oblique and settle kernels is byte-identical with and without it, that of the hopper
kernel too apart from the names numba gives its constant byte strings (a hash that
changes from process to process anyway). First run of scenarios/oblique.toml: 10.9 ->
8.2 s of CPU, settle.toml's kernel 19.5 -> 13.7 s, hopper.toml's 38.0 -> 24.5 s (2-core
AMD EPYC, empty caches, in-process).

2. Its compiler flags give their values without a Python call per option.

Why: typing a call to an overloaded function (every ``np.empty``, ``max``, tuple index
and the like, in every inlined copy) looks up the overload's implementation in a cache
keyed by, among others, the compiler's ``Flags`` (``numba.core.typing.templates``,
``_get_impl``). Hashing and comparing the key builds ``Flags.values()``, a dict of some
50 options, each read through its own Python property: three such dicts a lookup, and
the settle kernel's typing makes ~110,000 lookups (5.8 million property calls; cProfile
made them the largest cost of the compile, its overhead per call exaggerating them: the
real cost is below). ``values`` now merges the class's defaults with the options set,
in C (``{**defaults, **set}``): the same dict, key for key, so the hashes, the
comparisons and everything numba compiles are unchanged.
Counted in-process over a cold compile and run (empty caches, the helper off, 2-core AMD
EPYC, 2026-11-25): ``values()`` took 1.14 s of scenarios/settle.toml's (269,039 calls)
and 0.11-0.20 s of scenarios/oblique.toml's; now 0.24 s and 0.02 s. Most of settle's
falls in the kernel's compile, the critical path of its first run (minidem.engine.warmup).

3. Its typing resolves a call it has resolved before from a memo.

Why: typing a call of a numba function type (``operator.mul`` on two floats, ``max``,
``math.sqrt``, a tuple index: ``numba.core.types.functions.BaseFunction.get_call_type``)
tries the function's templates in order; each one that fails formats its error message
(every registered signature of a ``ConcreteTemplate`` as text) and the one that matches
selects among its cases. The kernel repeats the same few calls thousands of times (its
inlined helpers), and each repetition did all of that again. The memo is kept per
function type, keyed as numba keys its own cache of overload implementations
(``_OverloadFunctionTemplate._get_impl``): the typing context, the argument types
(literals included), the keyword arguments and the compiler flags in force; it holds the
signature and the implementation key the first resolution found, and a repetition sets
the implementation key again, as the resolution itself does (the lowering reads the last
one set). A resolution that fails is not kept (it raises again). First compile of the
settle kernel, in-process, 2-core AMD EPYC: 8.50-8.75 s against 10.19-11.59 s.

4. Python's garbage collector pauses while numba compiles.

Why: a compile allocates millions of small objects (IR, type maps, LLVM wrappers), and
every 700 net allocations start a collection; each third-generation one walks every
object the process holds, the more of them the more kernels it has compiled before. A
compile makes few reference cycles worth collecting before it ends, so the collector is
off from the start of numba's outermost compile to its end (``numba:compile`` events, a
compile that fails included) and as it was after: what the compile left is collected by
the next collection, as any garbage. First compile of scenarios/oblique.toml's kernel in
a fresh process (the helper off, 2-core AMD EPYC, alternating): 3.30, 3.80, 5.36, 4.45 s
of CPU against 4.02, 4.28, 5.80, 5.24 s; in a process that compiled it once before,
3.34 s against 4.55 (medians of four). The cost is memory while a compile runs, the
cycles it made held until it ends: a first run's peak 239 MB against 215 MB
(scenarios/oblique.toml), 499 MB against 420 MB (scenarios/hopper.toml, the largest
kernel; found by a reviewer). The collector is off for the whole process meanwhile (other
threads too), as numba compiles one function at a time anyway.

A numba whose internals no longer match (no ``copy`` module or no ``inline_ir`` in its
inliner; no ``TargetConfig.values`` or options without defaults; no compile events) is
left as it is: the kernels then compile as before, only slower.
"""

from __future__ import annotations

import copy
import functools
import gc

from numba.core import event, inline_closurecall, ir, targetconfig
from numba.core.types import functions


class _BlockCopier:
    """Stands in for the ``copy`` module inside numba's inliner: a deep copy of an IR
    block shares its memo with the other blocks of the same scope copied in the same
    ``inline_ir`` call (``memos`` is reset around every call, so a copy is never reused
    for a later inlining, which mutates its copy)."""

    # ``inline_ir`` copies the callee twice: the copy it inlines, and a copy of that copy
    # before it is changed, returned as the first item of its result "unmutated". Every
    # caller in numba (InlineInlinables through ``inline_function``, the typed inliner of
    # overloads) discards that item, so the second copy is not made: the item is then the
    # inlined copy itself. 0.15-0.2 s of CPU in the first run of scenarios/oblique.toml
    # (a twentieth of its kernel's compile), the IR numba goes on with unchanged.
    skip_discarded_copy = True

    def __init__(self):
        self.memos: dict[int, dict] | None = None
        # the blocks copied in the current inline_ir call, by id (kept alive here)
        self.made: dict[int, ir.Block] | None = None

    def __getattr__(self, name):
        return getattr(copy, name)

    def deepcopy(self, value, memo=None):
        if memo is None and self.memos is not None and isinstance(value, ir.Block):
            if self.skip_discarded_copy and self.made is not None and id(value) in self.made:
                return value  # the copy of a copy: the discarded "unmutated" callee
            # keyed by the scope's id: the memo keeps the scope alive, so the id is not reused
            made = copy.deepcopy(value, self.memos.setdefault(id(value.scope), {}))
            if self.made is not None:
                self.made[id(made)] = made
            return made
        return copy.deepcopy(value, memo)


def install() -> bool:
    """Install the repairs (idempotent); False when this numba is not the one they were
    written for (then nothing of it is touched)."""
    flags = _install_flag_values()
    memo = _install_call_memo()
    pause = _install_collector_pause()
    return _install_block_copier() and flags and memo and pause


def _install_call_memo() -> bool:
    """Wrap ``BaseFunction.get_call_type`` in the memo of repair 3 (idempotent); False
    when this numba's function types or its compiler's config stack are not the ones it
    was written for."""
    base = getattr(functions, "BaseFunction", None)
    plain = getattr(base, "get_call_type", None)
    stack = getattr(targetconfig, "ConfigStack", None)
    if plain is None or stack is None or not hasattr(stack, "top_or_none"):
        return False
    if getattr(plain, "_minidem_memo", False):
        return True

    @functools.wraps(plain)
    def get_call_type(self, context, args, kws):
        memo = self.__dict__.get("_minidem_calls")
        if memo is None:
            memo = self.__dict__["_minidem_calls"] = {}
        try:
            key = (context, args, tuple(kws.items()) if kws else (), stack.top_or_none())
            found = memo.get(key)
        except TypeError:  # an unhashable argument type: numba's own path
            return plain(self, context, args, kws)
        if found is not None:
            signature, impl_key = found
            self._impl_keys[signature.args] = impl_key
            return signature
        signature = plain(self, context, args, kws)
        if signature is not None:
            memo[key] = (signature, self._impl_keys[signature.args])
        return signature

    get_call_type._minidem_memo = True
    base.get_call_type = get_call_type
    return True


def _install_block_copier() -> bool:
    """Install the block copier into numba's inliner (idempotent); False when this numba's
    inliner is not the one it was written for."""
    worker = getattr(inline_closurecall, "InlineWorker", None)
    current = getattr(inline_closurecall, "copy", None)
    if isinstance(current, _BlockCopier):
        return True
    if current is not copy or worker is None or not hasattr(worker, "inline_ir"):
        return False
    copier = _BlockCopier()
    plain_inline_ir = worker.inline_ir

    @functools.wraps(plain_inline_ir)
    def inline_ir(self, *args, **kwargs):
        outer, copier.memos, outer_made, copier.made = copier.memos, {}, copier.made, {}
        try:
            return plain_inline_ir(self, *args, **kwargs)
        finally:
            copier.memos, copier.made = outer, outer_made

    worker.inline_ir = inline_ir
    inline_closurecall.copy = copier
    return True


def option_values(config) -> dict:
    """``config.values()`` (a ``TargetConfig``, numba's compiler ``Flags``): every option's
    value, the default where it is not set, in the class's option order. The defaults are
    read once per class (kept in its own ``__dict__``, so a subclass with other options
    keeps its own)."""
    cls = type(config)
    defaults = cls.__dict__.get("_minidem_option_defaults")
    if defaults is None:
        defaults = {name: option.default for name, option in cls.options.items()}
        setattr(cls, "_minidem_option_defaults", defaults)
    return {**defaults, **config._values}


def _install_flag_values() -> bool:
    """Make ``TargetConfig.values`` :func:`option_values` (idempotent), if it gives the
    same dict as numba's own for a fresh and a modified ``Flags``; False otherwise."""
    config = getattr(targetconfig, "TargetConfig", None)
    plain = getattr(config, "values", None)
    if plain is option_values:
        return True
    if plain is None:
        return False
    try:
        from numba.core.compiler import Flags

        probe = Flags()
        probe.nrt, probe.fastmath = True, True
        same = all(plain(flags) == option_values(flags) and list(plain(flags)) == list(option_values(flags))
                   for flags in (Flags(), probe))
    except Exception:  # a numba whose flags are built otherwise: leave them
        return False
    if not same:
        return False
    config.values = option_values
    return True



class _CollectorPause(event.Listener):
    """Repair 4: pauses Python's cyclic garbage collector from the start of numba's
    outermost compile to its end (a compile that raises included), and leaves it as it
    found it (a program that disabled it keeps it disabled). Compiles run one at a time
    (numba's compiler lock); a nested one (a function the kernel calls, compiled on the
    way) changes nothing."""

    def __init__(self):
        self.depth = 0
        self.resume = False

    def on_start(self, ev):
        if self.depth == 0:
            self.resume = gc.isenabled()
            gc.disable()
        self.depth += 1

    def on_end(self, ev):
        # never below zero: an end without its start (another listener raised before this
        # one was told of the start) must not leave the pause on for good
        self.depth = max(self.depth - 1, 0)
        if self.depth == 0 and self.resume:
            self.resume = False
            gc.enable()


_COLLECTOR_PAUSE = _CollectorPause()


def _install_collector_pause() -> bool:
    """Register repair 4's listener for numba's compile events (idempotent); False when
    this numba has no such events."""
    register = getattr(event, "register", None)
    if register is None:
        return False
    if not getattr(_COLLECTOR_PAUSE, "registered", False):
        register("numba:compile", _COLLECTOR_PAUSE)
        _COLLECTOR_PAUSE.registered = True
    return True
