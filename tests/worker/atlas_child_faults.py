"""A stand-in for the xatlas child (``worker.atlas.CHILD_MODULE``) that fails the way
xatlas has: TEXSPACE_TEST_ATLAS_FAULT = segfault | abort | hang."""
import ctypes
import os
import time

if __name__ == "__main__":
    fault = os.environ.get("TEXSPACE_TEST_ATLAS_FAULT")
    if fault == "segfault":
        ctypes.string_at(0)  # dereference NULL: SIGSEGV, like the xatlas bug
    elif fault == "abort":
        os.abort()
    elif fault == "hang":
        time.sleep(3600)
    raise SystemExit(f"unknown TEXSPACE_TEST_ATLAS_FAULT {fault!r}")
