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


def new_record(dtype: np.dtype) -> np.ndarray:
    """A zeroed record of ``dtype`` (a 1-element array): a plain structured array when the kernels are
    compiled, its ``numpy.recarray`` view when the JIT is disabled (same memory, fields by attribute)."""
    record = np.zeros(1, dtype)
    return record.view(np.recarray) if jit_disabled() else record
