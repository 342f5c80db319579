"""The one place that decides how minretarget's kernels are compiled.

Every kernel is decorated with ``kernel`` (serial) or ``parallel_kernel`` (``prange`` loops over
points). Compiled code is cached on disk next to the package, so only the first import on a
machine pays the compile time. fastmath allows reassociation and contraction (FMA) but keeps
NaN and inf semantics, so a bad value propagates instead of being optimised into garbage.
Set ``NUMBA_DISABLE_JIT=1`` to run every kernel as plain Python (the tests do this too).
"""
import numba

FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}

kernel = numba.njit(cache=True, fastmath=FASTMATH, nogil=True)
parallel_kernel = numba.njit(cache=True, fastmath=FASTMATH, nogil=True, parallel=True)
prange = numba.prange
