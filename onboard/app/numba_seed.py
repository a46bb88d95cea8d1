"""Compiled kernels (the estimator's, the image chain's) at a container's start: numba's cache seeded from the image.

numba loads compiled machine code only from a cache directory it can write (``NUMBA_CACHE_DIR``), and the image's
package tree is read-only at run time, so the image sets that directory in its ``/tmp`` tmpfs, which every start
finds empty: each start would compile the kernels again (seconds of CPU, more on a companion-class core) before the
first estimate, a restart in flight included. The image compiles them once when it is built, into a seed directory
(``IRTRACK_NUMBA_CACHE_SEED``); the daemon copies the seed's files into ``NUMBA_CACHE_DIR`` before it builds its
estimator. numba checks each cached entry against its source file's path, size and time stamp and against this
CPU, and compiles anew whatever does not match (an image built on another machine): a stale seed costs the compile
it would have saved, never a wrong kernel.
"""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Mapping

log = logging.getLogger(__name__)

__all__ = ["SEED_ENV", "seed_numba_cache"]

SEED_ENV = "IRTRACK_NUMBA_CACHE_SEED"


def seed_numba_cache(environ: Mapping[str, str] = os.environ) -> int:
    """Copy the files of ``environ[IRTRACK_NUMBA_CACHE_SEED]`` that ``environ[NUMBA_CACHE_DIR]`` lacks into it (both
    set, else nothing); the number of files copied.  A failure is logged once and costs only the compile."""
    seed, cache = environ.get(SEED_ENV), environ.get("NUMBA_CACHE_DIR")
    if not seed or not cache:
        return 0
    copied = 0
    try:
        for root, _dirs, files in os.walk(seed):
            target = os.path.join(cache, os.path.relpath(root, seed))
            os.makedirs(target, exist_ok=True)
            for name in files:
                dst = os.path.join(target, name)
                if not os.path.exists(dst):
                    shutil.copy2(os.path.join(root, name), dst)
                    copied += 1
    except OSError as exc:
        log.warning(
            "%s=%s: not copied into NUMBA_CACHE_DIR=%s (%s): the kernels compile at start", SEED_ENV, seed, cache, exc
        )
        return copied
    if copied:
        log.info("numba cache: %d compiled-kernel files seeded from %s into %s", copied, seed, cache)
    return copied
