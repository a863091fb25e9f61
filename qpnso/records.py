"""Records: the one-element NumPy structured arrays that the compiled kernels read by field.

The tick's state, parameters, memory, problem and solution are records (``tick_dtype`` and its parts);
Numba reads their fields by name.  Without the JIT (``NUMBA_DISABLE_JIT=1``: stepping through a kernel
in a debugger, mutation testing) the kernels run as Python, where an element of a plain structured
array is a ``numpy.void`` without attribute access: :func:`new_record` then returns a
``numpy.recarray`` view, whose elements (``numpy.record``) read and write their fields by attribute.
"""

from __future__ import annotations

import numpy as np

from qpnso.compiled_cache import jit_disabled

_DTYPES: dict[np.dtype, np.dtype] = {}


def interned(dtype: np.dtype) -> np.dtype:
    """The one object of the record types equal to ``dtype``: Numba's dispatcher types an argument quickly only
    if its dtype is the very object it has seen (a second controller's records, equal but new dtype objects,
    cost 10 µs instead of 1.3 µs per kernel call, about 45 µs a tick: measured on ``begin_tick``)."""
    return _DTYPES.setdefault(np.dtype(dtype), np.dtype(dtype))


def new_record(dtype: np.dtype) -> np.ndarray:
    """A zeroed record of ``dtype`` (a 1-element array, its type :func:`interned`): a plain structured array
    when the kernels are compiled, its ``numpy.recarray`` view when the JIT is disabled (same memory, fields by
    attribute)."""
    record = np.zeros(1, interned(dtype))
    return record.view(np.recarray) if jit_disabled() else record
