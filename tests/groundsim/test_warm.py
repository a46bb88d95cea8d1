"""``python -m groundsim.app.warm`` (``make demo``'s kernels step): what it compiles, and that it says so."""

from __future__ import annotations

import re
from pathlib import Path

from groundsim.app import warm

REPO = Path(__file__).resolve().parents[2]


def _cached_kernel_modules() -> list[Path]:
    """Every module of ours with a numba kernel cached on disk."""
    return sorted(
        p
        for top in ("onboard", "groundsim")
        for p in (REPO / top).rglob("*.py")
        if re.search(r"cache\s*=\s*True", p.read_text(encoding="utf-8"))
    )


def test_the_makefile_rewarms_when_any_cached_kernels_source_changes():
    """A kernel module outside the Makefile's prerequisites would leave its cache stale after an edit and the
    demo's first process compiling it again, silently: every one is matched by them."""
    line = next(
        ln for ln in (REPO / "Makefile").read_text(encoding="utf-8").splitlines() if ln.startswith("$(KERNELS):")
    )
    patterns = re.search(r"\$\(wildcard ([^)]*)\)", line).group(1).split()
    modules = _cached_kernel_modules()
    assert len(modules) >= 5, modules  # the estimator's, the image chain's, the renderer's three
    unmatched = [p.relative_to(REPO) for p in modules if not any(p.relative_to(REPO).match(pat) for pat in patterns)]
    assert unmatched == []


def test_every_onboard_kernel_module_is_warmed():
    """The simulator's kernels are warmed by rendering its scenes; the daemon's by name: each named here."""
    source = Path(warm.__file__).read_text(encoding="utf-8")
    onboard = [p for p in _cached_kernel_modules() if p.relative_to(REPO).parts[0] == "onboard"]
    assert onboard
    for p in onboard:
        dotted = ".".join(p.relative_to(REPO).with_suffix("").parts)
        package, module = dotted.rsplit(".", 1)
        assert f"from {package} import {module}" in source, dotted


def test_main_warms_both_parts_and_names_a_part_that_failed(capsys):
    assert warm.main(("P1",)) == 0
    out = capsys.readouterr().out
    assert "warm: the daemon's kernels" in out and "warm: the simulator's kernels (P1 rendered)" in out

    assert warm.main(("P1", "NOPE")) == 1
    captured = capsys.readouterr()
    assert "warm: the daemon's kernels" in captured.out  # the other part still done
    assert "warm: failed: ValueError: no shipped scenario NOPE (config/scenarios has P1, " in captured.err
