"""tasks.buffers.heap_arrays: inside it glibc serves arrays of a few megabytes from its heap; outside, the
process' fixed mmap threshold maps each afresh (a real process with the workers' malloc settings)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from tasks.buffers import _libc

SCRIPT = textwrap.dedent("""
    import numpy as np
    from tasks.buffers import heap_arrays

    def in_heap(a):
        address = a.__array_interface__["data"][0]
        for line in open("/proc/self/maps"):
            if line.rstrip().endswith("[heap]"):
                lo, hi = (int(x, 16) for x in line.split()[0].split("-"))
                return lo <= address < hi
        return False

    def placed():
        a = np.ones(8 << 20, dtype=np.uint8)         # 8 MiB, above the 4 MiB threshold
        return in_heap(a)

    before = placed()
    with heap_arrays():
        with heap_arrays():                          # nested: the outer one restores
            nested = placed()
        inside = placed()
    after = placed()
    print(before, nested, inside, after)
""")


@pytest.mark.skipif(not sys.platform.startswith("linux") or not _libc(), reason="glibc's mallopt is Linux/glibc only")
def test_arrays_come_from_the_heap_only_inside():
    env = {**os.environ, "MALLOC_MMAP_THRESHOLD_": "4194304", "MALLOC_TRIM_THRESHOLD_": str(8 << 20)}
    run = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=120,
                         cwd=os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["False", "True", "True", "False"]
