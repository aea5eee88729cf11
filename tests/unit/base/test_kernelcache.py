"""A cached numba kernel keyed on its callees' files (btmission.kernelcache) recompiles when one
of them changes; without the key it would load machine code built from the old callee."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

CALLER = """
from numba import njit
import callee
from callee import f
from btmission.kernelcache import key_on_callees

@njit(cache=True)
def g():
    return f() + 0

if {keyed}:
    key_on_callees([g], callee)
print(g())
"""


def _run(where: Path) -> str:
    env = dict(os.environ, PYTHONPATH=f"{where}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    out = subprocess.run(
        [sys.executable, str(where / "caller.py")], env=env, capture_output=True, text=True,
        timeout=120, check=True,
    )  # fmt: skip
    return out.stdout.strip()


@pytest.mark.parametrize("keyed", [True, False])
def test_a_changed_callee_recompiles_a_keyed_kernel(tmp_path: Path, keyed: bool) -> None:
    (tmp_path / "caller.py").write_text(textwrap.dedent(CALLER.format(keyed=keyed)))
    callee = tmp_path / "callee.py"
    callee.write_text("from numba import njit\n\n@njit(cache=True)\ndef f():\n    return 1\n")
    assert _run(tmp_path) == "1"
    assert _run(tmp_path) == "1"  # (loaded from the cache)
    callee.write_text("from numba import njit\n\n@njit(cache=True)\ndef f():\n    return 22\n")
    os.utime(callee, (os.stat(callee).st_atime, os.stat(callee).st_mtime + 5))
    # keyed: recompiled against the new callee; not keyed: numba's own key loads the old code
    assert _run(tmp_path) == ("22" if keyed else "1")
