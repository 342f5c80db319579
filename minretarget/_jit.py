"""The one place that decides how minretarget's kernels are compiled.

Every kernel is decorated with ``kernel``, serial: a stream runs one frame at a time. The
largest per-frame kernel besides SKR, linear blend skinning of 13,718 points, takes 0.8 ms
serial, so ``prange`` could save at most about half of that on 2 cores, and it cost more:
with numba's TBB threading layer every parallel call leaked about 7 kB (numba issue #10225:
70 MB per 10,000 frames), and with its OpenMP layer a frame took 9 to 16 times longer while
another process kept a core busy (threads waiting at the barrier). Compiled code is cached
on disk next to the package, so only the first import on a machine pays the compile time.
fastmath allows reassociation and contraction (FMA) but keeps NaN and inf semantics, so a
bad value propagates instead of being optimised into garbage. Set ``NUMBA_DISABLE_JIT=1``
to run every kernel as plain Python (the tests do this too).
"""
import contextlib

import numba
from numba.core import event

FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}

kernel = numba.njit(cache=True, fastmath=FASTMATH, nogil=True)


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
