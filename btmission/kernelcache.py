"""numba's on-disk cache keyed on the files a kernel calls into, not only its own.

``@njit(cache=True)`` stores a kernel's machine code next to its file and loads it again while
that file's stamp (modification time and size) is unchanged. A kernel that calls kernels of
other files is compiled with their code inlined, yet keyed on its own file alone: after one of
those files changed it would load machine code built from their old source and compute the old
thing, silently. :func:`key_on_callees` adds those files' stamps to its key, so that a change to
any of them recompiles it.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from types import ModuleType
from typing import Any


def key_on_callees(kernels: Iterable[Any], *modules: ModuleType) -> None:
    """Key the cache of each of ``kernels`` (numba dispatchers with ``cache=True``) on the
    stamps of ``modules``' files too (module docstring). Call it where the kernels are defined,
    before their first call; without numba's cache internals (another numba), it does nothing."""
    stamps = []
    for mod in modules:
        st = os.stat(str(mod.__file__))
        stamps.append((st.st_mtime, st.st_size))
    for kernel in kernels:
        try:
            index = kernel._cache._cache_file
            own = index._source_stamp
        except AttributeError:  # another numba's internals: its own key only
            continue
        index._source_stamp = (own, *stamps)
