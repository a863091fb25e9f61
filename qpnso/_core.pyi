"""
qpnso's C++ core: CasADi Functions evaluated without Python (the tick's port: src/core/PORTING.md).
"""

from collections.abc import Sequence
from typing import Annotated

import numpy
from numpy.typing import NDArray


def build_info() -> str: ...

class CasadiFunction:
    @staticmethod
    def load_compiled(library: str, name: str) -> CasadiFunction:
        """
        A Function from the shared library compiled from casadi.Function.generate's C (dlopen).
        """

    @staticmethod
    def load_runtime(libcasadi: str, serialized_file: str, name: str) -> CasadiFunction:
        """
        A Function saved by Function.save, evaluated by libcasadi's C API (dlopen).
        """

    @property
    def name(self) -> str: ...

    @property
    def runtime(self) -> str: ...

    @property
    def n_in(self) -> int: ...

    @property
    def n_out(self) -> int: ...

    def __call__(self, args: Sequence[Annotated[NDArray[numpy.float64], dict(order='F', device='cpu', writable=False)]]) -> list:
        """The outputs, as new column-major arrays of the outputs' shapes."""

    def eval_into(self, args: Sequence[Annotated[NDArray[numpy.float64], dict(order='F', device='cpu', writable=False)]], outputs: Sequence[Annotated[NDArray[numpy.float64], dict(order='F', device='cpu')]]) -> None:
        """
        Writes the outputs into the given float64 column-major arrays (no allocation, no copy).
        """

    def bind(self, args: Sequence[Annotated[NDArray[numpy.float64], dict(order='F', device='cpu')]], outputs: Sequence[Annotated[NDArray[numpy.float64], dict(order='F', device='cpu')]]) -> Bound:
        """
        An evaluation bound to these float64 column-major arrays, read and written where they lie on each call (a tick's: no argument to convert). The Bound keeps the arrays and the function alive.
        """

class Bound:
    def __call__(self) -> None:
        """Evaluates from the bound inputs into the bound outputs."""
