"""onboard.core.schema's YAML loader on hostile input: aliases, deep nesting and scalars their tag cannot read are
one-line errors naming the file, line and column, never a traceback, a RecursionError or minutes of expansion;
every YAML file irtrack ships still reads."""

from __future__ import annotations

import inspect
import sys
from pathlib import Path

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from groundsim.world.scenario import ScenarioError, load_scenario
from onboard.app.config import OnboardConfigError, load_config
from onboard.core.schema import MAX_YAML_DEPTH, SchemaError, YamlRefused, parse_yaml_text, read_yaml

REPO = Path(__file__).resolve().parents[2]
#: YAML files of the repository read by other programs than irtrack's loader (Docker Compose reads these, and
#: their ``x-`` anchors are how Compose shares a block)
NOT_OURS = {"deploy/compose.yaml", "deploy/compose.fleet.yaml"}
#: 9 levels of 9 aliases each: 400 bytes that PyYAML expands to 9^9 (387 million) strings
ALIAS_BOMB = "vehicle:\n  - &a0 [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"  - &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]\n" for i in range(1, 9)
)


def _write(tmp_path: Path, text: str, name: str = "c.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def _nested(levels: int) -> str:
    """A mapping whose one value is ``levels`` nested empty lists: ``levels + 1`` nodes deep."""
    return "a: " + "[" * levels + "]" * levels + "\n"


def _depth(value) -> int:
    """Nodes on the deepest path of a parsed document, scalars included (as the loader counts them)."""
    if isinstance(value, list):
        return 1 + max((_depth(v) for v in value), default=0)
    if isinstance(value, dict):
        return 1 + max((max(_depth(k), _depth(v)) for k, v in value.items()), default=0)
    return 1


SHIPPED = sorted(
    p.relative_to(REPO).as_posix()
    for root in ("config", "deploy", "onboard", "groundsim", "bench")
    for p in (REPO / root).rglob("*.y*ml")
)


def test_the_shipped_files_are_found():
    assert {"config/onboard.yaml", "config/scenarios/P1.yaml", "deploy/onboard.container.yaml"} <= set(SHIPPED)


@pytest.mark.parametrize("path", sorted(set(SHIPPED) - NOT_OURS))
def test_every_shipped_yaml_file_still_reads(path):
    data = read_yaml(REPO / path)
    assert isinstance(data, dict) and data, path
    assert _depth(data) <= MAX_YAML_DEPTH // 8  # far from the bound: the bound is not what a file needs


def test_the_compose_files_do_use_aliases_so_they_stay_docker_s():
    # were they read by irtrack's loader, these would be refused: the list above is not a stale exclusion
    for path in sorted(NOT_OURS):
        with pytest.raises(SchemaError, match=r": line \d+, column \d+: expected YAML without aliases"):
            read_yaml(REPO / path)


def test_nesting_is_read_up_to_the_bound_and_refused_beyond_it():
    assert _depth(parse_yaml_text(_nested(MAX_YAML_DEPTH - 1))) == MAX_YAML_DEPTH
    with pytest.raises(YamlRefused) as ei:
        parse_yaml_text(_nested(MAX_YAML_DEPTH))
    assert ei.value.problem == f"a value nested deeper than {MAX_YAML_DEPTH} levels"
    assert (ei.value.problem_mark.line, ei.value.problem_mark.column) == (0, 3 + MAX_YAML_DEPTH - 1)


@pytest.mark.parametrize("load, error", [(load_config, OnboardConfigError), (load_scenario, ScenarioError)])
def test_a_deeply_nested_file_is_one_line_naming_file_line_and_column(tmp_path, load, error):
    path = _write(tmp_path, _nested(5000))
    with pytest.raises(error) as ei:
        load(path, **({"environ": {}} if load is load_config else {}))
    assert str(ei.value) == (
        f"{path}: line 1, column {4 + MAX_YAML_DEPTH - 1}: expected YAML nested at most {MAX_YAML_DEPTH} levels "
        f"deep, got a value nested deeper than {MAX_YAML_DEPTH} levels"
    )
    assert ei.value.line == 1 and ei.value.exit_code == 2


def test_a_caller_deep_in_its_own_stack_gets_the_loader_error_not_a_recursion_error(tmp_path):
    path = _write(tmp_path, _nested(MAX_YAML_DEPTH - 1))
    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(len(inspect.stack(0)) + 60)  # the document needs about 3 frames a level: ~190
    try:
        with pytest.raises(SchemaError) as ei:
            read_yaml(path)
    finally:
        sys.setrecursionlimit(limit)
    assert str(ei.value) == (
        f"{path}: (file): expected YAML nested at most {MAX_YAML_DEPTH} levels deep, got a document too deeply nested"
    )
    assert _depth(read_yaml(path)) == MAX_YAML_DEPTH  # the same file with the stack to spare


def test_an_alias_bomb_is_refused_at_its_first_alias(tmp_path):
    path = _write(tmp_path, ALIAS_BOMB)
    assert len(ALIAS_BOMB) < 500
    with pytest.raises(OnboardConfigError) as ei:
        load_config(path, environ={})
    assert (
        str(ei.value)
        == f"{path}: line 3, column 10: expected YAML without aliases (write each value out), got the alias '*a0'"
    )
    assert ei.value.line == 3


def test_an_anchor_alone_is_harmless_and_read_but_a_merge_key_needs_an_alias():
    assert parse_yaml_text("a: &x 1\nb: [&y 2, 3]\n") == {"a": 1, "b": [2, 3]}
    with pytest.raises(YamlRefused, match=r"the alias '\*base'"):
        parse_yaml_text("base: &base {x: 1}\nc:\n  <<: *base\n  y: 2\n")


@pytest.mark.parametrize(
    "value, got",
    [
        ("2026-13-45", "got '2026-13-45' (month must be in 1..12)"),
        ("2026-02-30 10:00:00", "got '2026-02-30 10:00:00' (day is out of range for month)"),
        ("!!int x", "got 'x' (invalid literal for int() with base 10: 'x')"),
        ("!!float abc", "got 'abc' (could not convert string to float: 'abc')"),
        ("!!timestamp x", "got 'x'"),
        ("!!bool maybe", "got 'maybe'"),
        ("!!map [1]", "got a sequence"),
    ],
)
def test_a_scalar_its_tag_cannot_read_is_one_line_at_its_line(tmp_path, value, got):
    path = _write(tmp_path, f"name: P1\nstart: {value}\n")
    tag = value.split()[0] if value.startswith("!!") else "!!timestamp"
    with pytest.raises(SchemaError) as ei:
        read_yaml(path)
    assert str(ei.value) == f"{path}: line 2, column 8: expected a value its tag {tag} can read, {got}"


_SCALARS = st.one_of(st.integers(-(10**6), 10**6), st.text(alphabet="abc xyz", max_size=4), st.booleans(), st.none())
_TREES = st.recursive(
    _SCALARS,
    lambda kids: st.one_of(
        st.lists(kids, max_size=3), st.dictionaries(st.text(alphabet="xyz", min_size=1, max_size=3), kids, max_size=3)
    ),
    max_leaves=12,
)


@settings(max_examples=80, deadline=None)
@given(tree=_TREES, wraps=st.integers(0, MAX_YAML_DEPTH + 8))
def test_any_document_reads_back_exactly_when_within_the_bound(tree, wraps):
    doc = tree
    for _ in range(wraps):
        doc = [doc]
    text = yaml.safe_dump(doc)
    if _depth(doc) <= MAX_YAML_DEPTH:
        assert parse_yaml_text(text) == doc
    else:
        with pytest.raises(YamlRefused, match=f"nested deeper than {MAX_YAML_DEPTH} levels"):
            parse_yaml_text(text)
