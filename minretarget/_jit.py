"""The one place that decides how minretarget's kernels are compiled.

Every kernel is decorated with ``kernel``, serial: a stream runs one frame at a time, and
the per-frame kernels besides SKR are too short for threads to pay for themselves. ``prange``
cost more than it saved: numba's TBB threading layer leaks memory on every parallel call
(numba issue #10225), and with its OpenMP layer the threads wait at the barrier whenever
another process holds a core (the figures: docs/runtime_notes.md). Compiled code is cached
on disk next to the package, so only the first import on a machine pays the compile time
(and a retargeter shares it with a second process: ``_compile_ahead``).
fastmath allows reassociation and contraction (FMA) but keeps NaN and inf semantics, so a
bad value propagates instead of being optimised into garbage; for the same reason a division
by zero gives inf or nan, as in NumPy (``error_model="numpy"``), rather than numba's
Python-style check before every division (about 7 % of the compile time, issue 40). Set
``NUMBA_DISABLE_JIT=1`` to run every kernel as plain Python (the tests do this too).
"""
import contextlib

import numba
from numba.core import event

FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}

# No cfunc wrapper: it only serves a kernel passed as a first-class function value, which
# minretarget never does, and each one is compiled and cached beside its kernel (issue 40).
kernel = numba.njit(cache=True, fastmath=FASTMATH, nogil=True, no_cfunc_wrapper=True,
                    error_model="numpy")


class _First(event.Listener):
    def __init__(self, callback):
        self.callback = callback

    def on_start(self, event):
        callback, self.callback = self.callback, None
        if callback is not None:
            callback()

    def on_end(self, event):
        pass


@contextlib.contextmanager
def on_first_compile(callback):
    """Within: ``callback()`` runs once, just before numba first compiles a kernel. numba
    raises its "numba:compile" event only for a kernel it cannot load from the on-disk
    cache, so a warm cache (or ``NUMBA_DISABLE_JIT=1``) never calls it."""
    with event.install_listener("numba:compile", _First(callback)):
        yield
