"""Large blocks of memory go back to the system as soon as they are freed (glibc's malloc).

glibc serves a block of at least its mmap threshold with a mapping of its own, unmapped when
freed; below it, from a heap that shrinks only from its top. The threshold starts at 128 KiB and
rises to the size of every such block freed (up to 32 MiB), so after the first binary value of a
few megabytes is freed, every later one comes from the heap, and what many slow readers held
stays resident after they are gone: 60 readers stalled on a 3.9 MB value Set twice a second left
a gateway at 156 MB of RSS 40 s after they closed (112 MB before) over gRPC, and SSE likewise.
A fixed threshold of 1 MiB gave 97 → 272 → 105 MB (gRPC) and 101 → 362 → 104 MB (SSE): each
large value is its own mapping. A block under 1 MiB (a text value, a camera frame of a few
hundred kilobytes) stays on the heap, where reusing it costs no page faults.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

log = logging.getLogger(__name__)

#: mallopt's parameter for the mmap threshold (glibc's malloc.h); setting it also stops glibc
#: from raising it by itself.
M_MMAP_THRESHOLD = -3
#: Blocks of at least this many bytes get a mapping of their own.
LARGE_BLOCK_BYTES = 1024 * 1024


def return_large_blocks() -> bool:
    """Make glibc map every block of LARGE_BLOCK_BYTES or more on its own; False where the C
    library is not glibc (nothing changes there)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    if mallopt(M_MMAP_THRESHOLD, LARGE_BLOCK_BYTES) != 1:
        log.debug("mallopt(M_MMAP_THRESHOLD) refused; large blocks stay on the heap")
        return False
    return True
