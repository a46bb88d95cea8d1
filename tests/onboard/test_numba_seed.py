"""seed_numba_cache: the image's compiled kernels copied into numba's run-time cache directory."""

from __future__ import annotations

import logging

from onboard.app.numba_seed import SEED_ENV, seed_numba_cache


def _tree(root, files: dict[str, bytes]) -> None:
    for rel, data in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)


def test_missing_files_are_copied_and_present_ones_kept(tmp_path):
    seed, cache = tmp_path / "seed", tmp_path / "cache"
    _tree(seed, {"estimation_ab/kernels.f-1.py311.nbi": b"index", "estimation_ab/kernels.f-1.py311.1.nbc": b"code"})
    _tree(cache, {"estimation_ab/kernels.f-1.py311.nbi": b"newer index"})
    env = {SEED_ENV: str(seed), "NUMBA_CACHE_DIR": str(cache)}
    assert seed_numba_cache(env) == 1
    assert (cache / "estimation_ab/kernels.f-1.py311.1.nbc").read_bytes() == b"code"
    # what numba wrote at run time (or an earlier start copied) is never overwritten by the seed
    assert (cache / "estimation_ab/kernels.f-1.py311.nbi").read_bytes() == b"newer index"
    assert seed_numba_cache(env) == 0


def test_nothing_without_both_directories(tmp_path):
    seed = tmp_path / "seed"
    _tree(seed, {"a.nbi": b"x"})
    assert seed_numba_cache({SEED_ENV: str(seed)}) == 0
    assert seed_numba_cache({"NUMBA_CACHE_DIR": str(tmp_path / "cache")}) == 0
    assert not (tmp_path / "cache").exists()


def test_an_unwritable_cache_is_logged_not_raised(tmp_path, caplog):
    seed = tmp_path / "seed"
    _tree(seed, {"a.nbi": b"x"})
    blocker = tmp_path / "file"
    blocker.write_bytes(b"")  # a file where the cache directory should be: makedirs fails
    with caplog.at_level(logging.WARNING, logger="onboard.app.numba_seed"):
        assert seed_numba_cache({SEED_ENV: str(seed), "NUMBA_CACHE_DIR": str(blocker / "cache")}) == 0
    assert len(caplog.records) == 1 and "the kernels compile at start" in caplog.records[0].getMessage()
