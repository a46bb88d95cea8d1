"""Every error irtrack raises on purpose survives pickling (a process pool sends a worker's error to its parent
pickled): the same class, message and attributes, whatever arguments its constructor takes."""

from __future__ import annotations

import ast
import copy
import pickle
from pathlib import Path

import pytest

from groundsim.world.scenario import ScenarioError
from onboard.app.config import OnboardConfigError
from onboard.app.track_video import OutputError
from onboard.core.errors import ConfigError, InputError, IrtrackError
from onboard.core.irframe import IrFrameError
from onboard.core.schema import SchemaError
from onboard.io.mavlink_signing import SigningKeyError
from onboard.io.mcap_read import RecordDamage
from onboard.pipeline.frame_pipeline import FrameRejected

REPO = Path(__file__).resolve().parents[2]

#: one instance of each IrtrackError subclass whose constructor takes other arguments than the message
ERRORS = [
    SchemaError("c.yaml", "mavlink.port", "an integer in [1, 65535]", "0", "did you mean 1?", line=3, keys=("a",)),
    OnboardConfigError("c.yaml", "estimator.window_s", "a number in (0, 600]", "-1", "hint"),
    ScenarioError("P9.yaml", "ir.noise_bank_frames", "an integer in [1, 64]", 100000, got_text=None, line=7),
    ScenarioError.make("<dict>", "duration_s", "a number", "'x'"),
    SchemaError("c.yaml", "a", "b", "c").as_(OnboardConfigError, "other.yaml", "section"),
    IrFrameError("short", "frame of 3 bytes: shorter than its header"),
    FrameRejected("dims_mismatch", "frame 640 x 480, expected 640 x 512"),
    OutputError("out/track.csv", "Permission denied"),
    SigningKeyError("mavlink.signing_key_file", "a readable key file", "'/k': Permission denied"),
    RecordDamage("a chunk's opcode 0x07 at byte 1357177, where the data section holds no message index", 1357177),
]


def _custom_constructors() -> set[str]:
    """Names of the classes of onboard, groundsim and bench deriving (by name) from IrtrackError that define
    ``__init__``: the ones Exception's own pickling cannot rebuild."""
    bases: dict[str, set[str]] = {}
    has_init: set[str] = set()
    for root in ("onboard", "groundsim", "bench"):
        for path in (REPO / root).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.ClassDef):
                    names = {b.id if isinstance(b, ast.Name) else getattr(b, "attr", "") for b in node.bases}
                    bases.setdefault(node.name, set()).update(names)
                    if any(isinstance(s, ast.FunctionDef) and s.name == "__init__" for s in node.body):
                        has_init.add(node.name)
    family = {"IrtrackError"}
    while True:
        more = {name for name, b in bases.items() if b & family} - family
        if not more:
            break
        family |= more
    return family & has_init


def test_the_list_covers_every_error_with_its_own_constructor():
    assert _custom_constructors() == {type(e).__name__ for e in ERRORS}


@pytest.mark.parametrize("err", ERRORS, ids=lambda e: f"{type(e).__name__}:{str(e)[:30]}")
def test_an_error_round_trips_through_pickle(err):
    back = pickle.loads(pickle.dumps(err))
    assert type(back) is type(err) and str(back) == str(err) and back.args == err.args
    assert vars(back) == vars(err)
    assert isinstance(back, IrtrackError) and isinstance(back, (ConfigError, InputError))
    assert str(copy.copy(err)) == str(err)  # copy takes the same path


def test_a_schema_error_keeps_what_its_callers_read():
    err = pickle.loads(pickle.dumps(ERRORS[2]))
    assert (err.source, err.field, err.got, err.line, err.exit_code) == (
        "P9.yaml",
        "ir.noise_bank_frames",
        "100000",
        7,
        2,
    )
    assert str(err) == "P9.yaml: ir.noise_bank_frames: expected an integer in [1, 64], got 100000"


def _raise_in_worker(which: int) -> None:
    raise ERRORS[which]


def test_an_error_raised_in_a_process_pool_worker_reaches_the_parent_as_itself():
    import concurrent.futures as cf
    import multiprocessing as mp

    with cf.ProcessPoolExecutor(1, mp_context=mp.get_context("spawn")) as pool:
        future = pool.submit(_raise_in_worker, 2)
        with pytest.raises(ScenarioError, match=r"^P9\.yaml: ir\.noise_bank_frames: expected an integer in \[1, 64\]"):
            future.result(timeout=120)
