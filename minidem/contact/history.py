"""The per-contact history a law's force function receives (``history``).

A contact's history is a handful of float64 slots the law reads and writes (its
``HistorySlot`` declarations, in order). The kernel keeps them where its loops want
them: a wall contact's in a row of an (entries, slots) array, a pair contact's in a
column of a (slots, contacts) tile, slot-major, so that the loop evaluating a tile of
contacts reads each slot of consecutive contacts from consecutive memory and LLVM can
compile it to vector code, several contacts at a time. A numpy view of a column would
serve the law as well, but its address arithmetic goes through the column's run-time
stride, which keeps the loop scalar (measured: a flat Hertz-Mindlin loop 34 ns a
contact either way with views, 7 ns with this type, the same bits).

So the law gets a ``ContactHistory``: slot ``s`` at ``data[s * step]``. In compiled
code it supports what a law needs of its history row:

    history[s]            read slot s (s >= 0; no wrap-around, no bounds check)
    history[s] = value    write it
    history[a:b]          the slots a..b-1 as a ContactHistory (what a composed law
                          hands each part); no step
    history[a:b] = value  set them all
    len(history)          the number of slots

It is not a numpy array: numpy functions do not take it (copy slots to locals first).
Called from Python (``minidem verify``, tests) a law gets a numpy array instead,
which supports the same operations.
"""

import operator

import numba
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic, models, overload, register_model


class ContactHistoryType(types.Type):
    def __init__(self):
        super().__init__(name="ContactHistory")


contact_history = ContactHistoryType()


@register_model(ContactHistoryType)
class _ContactHistoryModel(models.StructModel):
    def __init__(self, dmm, fe_type):
        members = [("data", types.CPointer(types.float64)), ("step", types.intp), ("size", types.intp)]
        super().__init__(dmm, fe_type, members)


def _history(context, builder, data, step, size):
    out = cgutils.create_struct_proxy(contact_history)(context, builder)
    out.data, out.step, out.size = data, step, size
    return out._getvalue()


def _element_pointer(context, builder, array_type, array, indices):
    """The address of array[indices] for a C-contiguous array: a GEP from its data
    pointer (so alias analysis knows which array it is in)."""
    ary = context.make_array(array_type)(context, builder, array)
    shape = cgutils.unpack_tuple(builder, ary.shape, array_type.ndim)
    strides = cgutils.unpack_tuple(builder, ary.strides, array_type.ndim)
    return cgutils.get_item_pointer2(context, builder, ary.data, shape, strides, "C", indices), shape


def _c_float_array(array, ndim):
    return isinstance(array, types.Array) and array.ndim == ndim and array.layout == "C" \
        and array.dtype == types.float64


@intrinsic
def history_row(typingctx, array, index):
    """Row ``index`` of a C-contiguous (entries, slots) float64 array."""
    if not (_c_float_array(array, 2) and isinstance(index, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        index_value = context.cast(builder, args[1], signature.args[1], types.intp)
        zero = context.get_constant(types.intp, 0)
        pointer, shape = _element_pointer(context, builder, signature.args[0], args[0], [index_value, zero])
        return _history(context, builder, pointer, context.get_constant(types.intp, 1), shape[1])

    return contact_history(array, index), codegen


@intrinsic
def history_row_of(typingctx, array, first, second):
    """Row [first, second] of a C-contiguous (n, m, slots) float64 array."""
    if not (_c_float_array(array, 3) and isinstance(first, types.Integer) and isinstance(second, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        first_value = context.cast(builder, args[1], signature.args[1], types.intp)
        second_value = context.cast(builder, args[2], signature.args[2], types.intp)
        zero = context.get_constant(types.intp, 0)
        pointer, shape = _element_pointer(context, builder, signature.args[0], args[0],
                                          [first_value, second_value, zero])
        return _history(context, builder, pointer, context.get_constant(types.intp, 1), shape[2])

    return contact_history(array, first, second), codegen


@intrinsic
def history_column(typingctx, tile, column, columns):
    """Column ``column`` of a C-contiguous (slots, columns) float64 tile, whose number of
    columns the caller passes: a compile-time constant there lets LLVM see that the
    slots of consecutive contacts do not overlap (with the tile's run-time shape it
    checks at run time, and the check fails on the slot a law reads and then writes:
    the vector loop never ran)."""
    if not (_c_float_array(tile, 2) and isinstance(column, types.Integer) and isinstance(columns, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        column_value = context.cast(builder, args[1], signature.args[1], types.intp)
        zero = context.get_constant(types.intp, 0)
        pointer, shape = _element_pointer(context, builder, signature.args[0], args[0], [zero, column_value])
        return _history(context, builder, pointer, context.cast(builder, args[2], signature.args[2], types.intp),
                        shape[0])

    return contact_history(tile, column, columns), codegen


def _slot_pointer(context, builder, history, index_type, index):
    h = cgutils.create_struct_proxy(contact_history)(context, builder, value=history)
    index_value = context.cast(builder, index, index_type, types.intp)
    return builder.gep(h.data, [builder.mul(index_value, h.step)]), h


@intrinsic
def _load(typingctx, history, index):
    def codegen(context, builder, signature, args):
        pointer, _ = _slot_pointer(context, builder, args[0], signature.args[1], args[1])
        return builder.load(pointer)

    return types.float64(history, index), codegen


@intrinsic
def _store(typingctx, history, index, value):
    def codegen(context, builder, signature, args):
        pointer, _ = _slot_pointer(context, builder, args[0], signature.args[1], args[1])
        builder.store(context.cast(builder, args[2], signature.args[2], types.float64), pointer)
        return context.get_dummy_value()

    return types.none(history, index, value), codegen


@intrinsic
def _size(typingctx, history):
    def codegen(context, builder, signature, args):
        return cgutils.create_struct_proxy(contact_history)(context, builder, value=args[0]).size

    return types.intp(history), codegen


@intrinsic
def _part(typingctx, history, start, stop):
    def codegen(context, builder, signature, args):
        pointer, h = _slot_pointer(context, builder, args[0], signature.args[1], args[1])
        size = builder.sub(context.cast(builder, args[2], signature.args[2], types.intp),
                           context.cast(builder, args[1], signature.args[1], types.intp))
        return _history(context, builder, pointer, h.step, size)

    return contact_history(history, start, stop), codegen


@overload(len)
def _len(history):
    if isinstance(history, ContactHistoryType):
        return lambda history: _size(history)


@numba.njit(inline="always")
def _bounds(index, size):
    """The slots of a step-less slice as Python counts them (a negative bound counts from
    the end; an empty part where the stop is not past the start), written so that a
    constant start stays a compile-time constant: a start beyond the size is not pulled
    back to it (the part is empty all the same).

    Why: a composed law hands each part the constant slice of its slots. Clipped against
    the run-time size as ``slice.indices`` clips it, the start (the slots' address) was
    known only at run time, LLVM could not tell a part's slots from those the kernel
    rotates (the same memory), checked at run time whether they overlap, and always ran
    the tile's loop scalar (settle scene, hm+epsd+sds_twisting: 1.6x slower a step)."""
    start = index.start + size if index.start < 0 else index.start
    stop = index.stop + size if index.stop < 0 else index.stop
    start = max(start, 0)
    return start, max(min(stop, size), start)


@overload(operator.getitem)
def _getitem(history, index):
    if not isinstance(history, ContactHistoryType):
        return None
    if isinstance(index, types.Integer):
        return lambda history, index: _load(history, index)
    if isinstance(index, types.SliceType) and not index.has_step:
        def part(history, index):
            start, stop = _bounds(index, _size(history))
            return _part(history, start, stop)
        return part
    return None


@overload(operator.setitem)
def _setitem(history, index, value):
    if not isinstance(history, ContactHistoryType):
        return None
    if isinstance(index, types.Integer) and isinstance(value, (types.Float, types.Integer)):
        return lambda history, index, value: _store(history, index, value)
    if isinstance(index, types.SliceType) and not index.has_step and isinstance(value, (types.Float, types.Integer)):
        def fill(history, index, value):
            start, stop = _bounds(index, _size(history))
            for s in range(start, stop):
                _store(history, s, value)
        return fill
    return None
