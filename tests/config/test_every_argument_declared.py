"""Every numeric or list argument of every registered component declares its rule, and every rule is enforced.

Generated from the registry: the core's components, every installed plugin's, and the example plugin's
(loaded from ``plugins/example`` when it is not installed). An argument whose annotation is numeric
(``int``, ``float``) or list-like (``list``, ``tuple``, ``Sequence``), looked at through ``Annotated``
and ``X | None``, must declare a constraint (``occplug.constraints``) on itself or on its
elements, or stand on :data:`ALLOWED` below with the reason it takes any value. Nested component
nodes (``Slot``) and the arguments a kind's contract fills in (``given``) are not config values of
the component and are skipped.
"""

from __future__ import annotations

import ast
import collections.abc as cabc
import importlib
import inspect
import sys
import types
import typing
from importlib import metadata, util
from pathlib import Path
from typing import Any, Literal

import pytest

from occplug.config import ConfigError
from occplug.config.validate import _Validator
from occplug.constraints import Constraint, Length, check_choices, choices_of, constraints_of, violated
from occplug.kinds import given_arguments
from occplug.plugins import ENTRY_POINT_GROUP, isolated
from occplug.settings import settings_type
from occplug.slots import component_params, slot_of

EXAMPLE_SRC = Path(__file__).resolve().parents[2] / "plugins" / "example" / "src"

#: (kind, component, argument) -> why the argument takes any value of its type (no constraint to declare).
ALLOWED: dict[tuple[str, str, str], str] = {
    # a Python index into timm's feature levels: -1 (the default) is the deepest, any int is meaningful to timm
    ("encoder", "timm", "feature_level"): "an index into timm's feature levels; negative counts from the deepest",
    # camera names, not numbers; each is checked against the prepared index when the data module is built
    ("data", "occ3d_nuscenes", "cameras"): "camera names checked against the index; [] or null = every camera",
    # signed frame offsets (negative = past); pipeline.check_offsets rejects 0 and repeats, no range applies
    ("data", "occ3d_nuscenes", "adjacent_offsets"): "signed frame offsets (negative: earlier frames)",
    ("data", "semantickitti", "adjacent_offsets"): "signed frame offsets (negative: earlier frames)",
    ("data", "synthetic", "adjacent_offsets"): "signed frame offsets (negative: earlier frames)",
    # signed frame offsets of past frames the model encodes; OccModel rejects 0 and repeats, no range applies
    ("model", "occ_model", "input_history"): "signed frame offsets (negative: earlier frames)",
    ("scene", "occle_scene", "history"): "signed frame offsets, each one of model.input_history",
    # nodes of kind 'transform', built and checked one by one by occplug.data.extensions
    ("data", "occ3d_nuscenes", "transforms"): "a list of transform nodes, checked by occplug.data.extensions",
    ("data", "semantickitti", "transforms"): "a list of transform nodes, checked by occplug.data.extensions",
    ("data", "synthetic", "transforms"): "a list of transform nodes, checked by occplug.data.extensions",
    # the view transform's own bin centres, handed in by lss (a contract value, not a user's setting)
    ("depth_net", "oracle_depth", "depth_centers"): "bin centres the view transform hands in; checked against num_bins",
    # a random seed: every int (negative too) is a valid seed
    ("data", "synthetic", "seed"): "a random seed; any int is one",
    # class names (strings), checked against the data set's classes when the metric is built
    ("metric", "occ3d_miou", "dynamic_classes"): "class names, checked against the data set's classes",
    ("metric", "occ3d_miou", "static_classes"): "class names, checked against the data set's classes",
    ("metric", "occ3d_miou", "exclude_classes"): "class names, checked against the data set's classes",
    ("metric", "rayiou", "dynamic_classes"): "class names, checked against the data set's classes",
    ("metric", "rayiou", "static_classes"): "class names, checked against the data set's classes",
    ("metric", "rayiou", "exclude_classes"): "class names, checked against the data set's classes",
    ("metric", "ssc", "exclude_classes"): "class names, checked against the data set's classes",
    # indices into the validation set, Python style: negative counts from the end, out of range is skipped
    ("callback", "bev_panel_logger", "samples"): "validation-set indices; negative counts from the end",
}

_UNION = (typing.Union, types.UnionType)
_LISTS = (list, tuple, cabc.Sequence)


def _alternatives(annotation: Any) -> list[Any]:
    """The plain types an annotation admits, through ``Annotated`` and ``X | None`` (``None`` left out)."""
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _alternatives(typing.get_args(annotation)[0])
    if origin in _UNION:
        return [t for arg in typing.get_args(annotation) if arg is not type(None) for t in _alternatives(arg)]
    return [annotation]


def _is_numeric_or_list(annotation: Any) -> bool:
    for t in _alternatives(annotation):
        if t in (int, float) or t in _LISTS or typing.get_origin(t) in _LISTS:
            return True
    return False


def _element(annotation: Any) -> Any | None:
    """The element annotation of the list-like alternative of ``annotation``, if it names one."""
    for t in _alternatives(annotation):
        if typing.get_origin(t) in _LISTS and typing.get_args(t):
            return typing.get_args(t)[0]
    return None


def _element_rules(annotation: Any) -> list[Constraint]:
    element = _element(annotation)
    return [] if element is None else constraints_of(element)


@pytest.fixture(scope="module")
def registry():
    """Core + every installed plugin + the example plugin (from its source tree if not installed)."""
    installed = sorted({ep.name for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)})
    extra: list[tuple[str, object]] = []
    loaded_here = util.find_spec("occplug_example") is None
    if loaded_here:
        sys.path.insert(0, str(EXAMPLE_SRC))
        try:
            extra.append(("example", importlib.import_module("occplug_example.plugin")))
        finally:
            sys.path.remove(str(EXAMPLE_SRC))
    with isolated(installed, extra) as reg:
        yield reg
    if loaded_here:  # leave no trace of the source-tree import for later tests
        for name in [m for m in sys.modules if m == "occplug_example" or m.startswith("occplug_example.")]:
            del sys.modules[name]


def _config_arguments(registry):
    """``(kind, name, argument, annotation, default)`` of every argument a config sets (no slots, no given)."""
    for entry in registry.entries():
        given = given_arguments(entry.kind, entry.factory)
        for key, (param, annotation) in component_params(entry.factory).items():
            if key in given or slot_of(annotation) is not None:
                continue
            yield entry.kind, entry.name, key, annotation, param.default


def test_every_numeric_or_list_argument_declares_a_rule(registry):
    checked, offenders = [], []
    for kind, name, key, annotation, _ in _config_arguments(registry):
        if not _is_numeric_or_list(annotation) or (kind, name, key) in ALLOWED:
            continue
        declared = constraints_of(annotation) + _element_rules(annotation)
        if declared:
            checked.append((kind, name, key))
        else:
            offenders.append(f"{kind} {name}.{key}: {annotation}")
    assert not offenders, (
        "arguments without a declared constraint (annotate them, e.g. Annotated[int, Positive], "
        "or add them to ALLOWED with the reason):\n  " + "\n  ".join(offenders)
    )
    # the rule is not met by nothing being checked: the core's and the example plugin's arguments are
    assert {("encoder", "small_cnn", "out_channels"), ("head", "tiny_mlp", "hidden")} <= set(checked)
    assert len(checked) >= 40, checked


def test_allow_list_is_not_stale(registry):
    arguments = {(kind, name, key): annotation for kind, name, key, annotation, _ in _config_arguments(registry)}
    stale = []
    for k in ALLOWED:
        if k not in arguments:
            stale.append(f"{k}: no such config argument")
        elif not _is_numeric_or_list(arguments[k]):
            stale.append(f"{k}: neither numeric nor a list")
        elif constraints_of(arguments[k]) + _element_rules(arguments[k]):
            stale.append(f"{k}: it declares a rule now")
    assert not stale, stale
    assert all(reason.strip() for reason in ALLOWED.values())


def _declared(registry):
    """``(kind, name, key, annotation, default)`` of every argument with a declared rule, given ones included."""
    out = []
    for entry in registry.entries():
        for key, (param, annotation) in component_params(entry.factory).items():
            if slot_of(annotation) is None and constraints_of(annotation) + _element_rules(annotation):
                out.append((entry.kind, entry.name, key, annotation, param.default))
    return out


def _bad_values(annotation: Any) -> list[Any]:
    """Values of each declared rule's :meth:`~Constraint.violations`: on the argument, and inside a list."""
    rules = constraints_of(annotation)
    bad = [v for rule in rules for v in rule.violations()]
    lengths = [r for r in rules if isinstance(r, Length)]
    n = 1
    if lengths:
        n = lengths[0].exact if lengths[0].exact is not None else max(lengths[0].min or 1, 1)
    for rule in _element_rules(annotation):
        bad += [[v] * n for v in rule.violations()]
    return bad


def test_declared_rules_cover_all_components_kinds(registry):
    kinds = {kind for kind, *_ in _declared(registry)}
    assert {
        "encoder",
        "view_transform",
        "depth_net",
        "scene",
        "head",
        "supervision",
        "data",
        "metric",
        "callback",
    } <= kinds


def test_every_declared_rule_is_one_clean_error_naming_the_key(registry):
    cases = 0
    for kind, name, key, annotation, default in _declared(registry):
        if default is not inspect.Parameter.empty:  # the defaults keep their behaviour: they satisfy the rules
            assert violated(list(default) if isinstance(default, tuple) else default, annotation) is None, (
                kind,
                name,
                key,
                default,
            )
        values = _bad_values(annotation)
        assert values, (kind, name, key)
        for bad in values:
            with pytest.raises(ConfigError) as caught:
                _Validator(registry).node({"type": name, key: bad}, kind, "x")
            message = str(caught.value)
            assert message.startswith(f"x.{key}: expected "), (kind, name, key, bad, message)
            assert "\n" not in message and "Traceback" not in message, message
            cases += 1
    assert cases >= 100, cases


@pytest.mark.parametrize(
    ("kind", "name", "key", "bad", "line"),
    [
        ("encoder", "small_cnn", "out_channels", 0, "x.out_channels: expected an int > 0, got int 0"),
        ("scene", "dense_voxels", "num_blocks", -1, "x.num_blocks: expected an int >= 0, got int -1"),
        ("supervision", "voxel_ce", "weight", -0.5, "x.weight: expected a number >= 0, got float -0.5"),
        (
            "supervision",
            "voxel_ce",
            "label_smoothing",
            1.5,
            "x.label_smoothing: expected a number in [0, 1], got float 1.5",
        ),
        (
            "scene",
            "dense_voxels_history",
            "history_weight",
            1.0,
            "x.history_weight: expected a number in (0, 1), got float 1.0",
        ),
        (
            "view_transform",
            "lss",
            "depth_bins",
            [1.0, 45.0],
            "x.depth_bins: expected a list of 3, got list [1.0, 45.0]",
        ),
        ("data", "synthetic", "batch_size", 0, "x.batch_size: expected an int > 0, got int 0"),
        (
            "data",
            "synthetic",
            "image_size",
            [2, 8],
            "x.image_size: expected every element an int >= 4, got list [2, 8]",
        ),
        (
            "metric",
            "rayiou",
            "thresholds",
            [1.0, -2.0],
            "x.thresholds: expected every element a number > 0, got list [1.0, -2.0]",
        ),
        ("head", "tiny_mlp", "hidden", -1, "x.hidden: expected an int > 0, got int -1"),
    ],
)
def test_known_lines(registry, kind, name, key, bad, line):
    with pytest.raises(ConfigError) as caught:
        _Validator(registry).node({"type": name, key: bad}, kind, "x")
    assert str(caught.value) == line


def test_hidden_zero_stays_valid_where_it_means_a_1x1_conv(registry):
    """``hidden: 0`` (a single 1x1 conv) is accepted by lss, backward_projection, plain and voxel_classifier."""
    v = _Validator(registry)
    grid = {"range": [-2.0, -2.0, 0.0, 2.0, 2.0, 0.8], "voxel_size": 0.4}
    for kind, node in [
        ("view_transform", {"type": "lss", "grid": grid}),
        ("view_transform", {"type": "backward_projection", "grid": grid}),
        ("depth_net", {"type": "plain"}),
        ("head", {"type": "voxel_classifier"}),
    ]:
        v.node({**node, "hidden": 0}, kind, "x")  # passes: no error at all
    with pytest.raises(ConfigError, match=r"^x.hidden: expected an int > 0, got int 0$"):
        v.node({"type": "camera_aware", "hidden": 0}, "depth_net", "x")


# ---------------------------------------------------------------------------------------------- choices


def _choice_arguments(registry):
    """``(kind, name, path, annotation)`` of every ``Literal``-annotated argument, inside settings groups too.

    ``path`` is the argument's keys from the component node down (``("query_agg", "coverage")``).
    """
    for entry in registry.entries():
        stack = [((key,), annotation) for key, (_, annotation) in component_params(entry.factory).items()]
        while stack:
            path, annotation = stack.pop()
            if slot_of(annotation) is not None:
                continue
            if choices_of(annotation):
                yield entry.kind, entry.name, path, annotation
            group = settings_type(annotation)
            if group is not None:
                stack += [((*path, k), a) for k, (_, a) in component_params(group).items()]


def _outside(choices: tuple[Any, ...]) -> Any:
    """A value none of ``choices`` is: a near miss of the first string choice, else one past the largest int."""
    strings = [c for c in choices if isinstance(c, str)]
    return strings[0] + "x" if strings else max(c for c in choices if isinstance(c, int)) + 1


def test_every_choice_outside_its_literal_is_one_line_at_config_validation(registry):
    seen = set()
    for kind, name, path, annotation in _choice_arguments(registry):
        choices = choices_of(annotation)
        bad = _outside(choices)
        node: Any = bad
        for key in reversed(path):
            node = {key: node}
        with pytest.raises(ConfigError) as caught:
            _Validator(registry).node({"type": name, **node}, kind, "x")
        message = str(caught.value)
        where = "x." + ".".join(path)
        assert message.startswith(f"{where}: expected ") and f"got {type(bad).__name__} {bad!r}" in message, message
        assert all(repr(c) in message for c in choices), message
        assert "\n" not in message and "Traceback" not in message, message
        if isinstance(bad, str):  # a near miss names the choice it missed
            assert message.endswith(f"; did you mean {bad[:-1]!r}?"), message
        seen.add((name, path[-1]))
    # the choices the constructors used to check by hand are among them, in the core and in each method plugin
    assert {
        ("small_cnn", "stride"),
        ("voxel_ce", "normalize"),
        ("lss", "splat"),
        ("dense_voxels_history", "reset"),
        ("duocc_stream", "fusion"),
        ("duocc_stream", "coverage"),
        ("occle_scene", "compute"),
        ("occle_projection_head", "mode"),
        ("queryocc_query_points", "points"),
        ("queryocc_render_points", "spacing"),
        ("queryocc_lift_contract_splat", "bins"),
    } <= seen, seen


def _hand_checked_choices(tree: ast.AST) -> list[int]:
    """Lines where an ``__init__`` raises when a parameter is ``not in`` a literal or module-level string tuple."""
    tuples = {
        target.id
        for node in getattr(tree, "body", [])
        if isinstance(node, (ast.Assign, ast.AnnAssign)) and _string_collection(node.value)
        for target in (node.targets if isinstance(node, ast.Assign) else [node.target])
        if isinstance(target, ast.Name)
    }
    lines = []
    for fn in ast.walk(tree):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)) or fn.name != "__init__":
            continue
        params = {a.arg for a in [*fn.args.args, *fn.args.kwonlyargs]}
        for branch in ast.walk(fn):
            if not isinstance(branch, ast.If) or not any(isinstance(n, ast.Raise) for n in branch.body):
                continue
            for cmp in ast.walk(branch.test):
                if not isinstance(cmp, ast.Compare) or not (isinstance(cmp.left, ast.Name) and cmp.left.id in params):
                    continue
                for op, right in zip(cmp.ops, cmp.comparators, strict=True):
                    named = isinstance(right, ast.Name) and right.id in tuples
                    if isinstance(op, ast.NotIn) and (named or _string_collection(right)):
                        lines.append(cmp.lineno)
    return lines


def _string_collection(node: ast.AST | None) -> bool:
    return (
        isinstance(node, (ast.Tuple, ast.Set, ast.List))
        and bool(node.elts)
        and all(isinstance(e, ast.Constant) and isinstance(e.value, str) for e in node.elts)
    )


def test_no_component_checks_a_string_choice_by_hand(registry):
    """Components declare choices as ``Literal`` and check them with ``check_choices``, not with a second tuple.

    Scanned: the module of every registered component and every module of the method plugins (their blocks too).
    """
    root = Path(__file__).resolve().parents[2]
    files = {Path(inspect.getsourcefile(entry.factory)).resolve() for entry in registry.entries()}
    for package in sorted((root / "plugins").glob("occplug_*")):
        files |= {p.resolve() for p in package.rglob("*.py") if "tests" not in p.relative_to(package).parts}
    offenders = [f"{path}:{n}" for path in sorted(files) for n in _hand_checked_choices(ast.parse(path.read_text()))]
    assert len(files) > 60, len(files)
    assert not offenders, "string choices checked by hand (annotate Literal[...], call check_choices):\n  " + (
        "\n  ".join(offenders)
    )


def test_the_hand_check_finder_finds_the_old_pattern():
    old = 'MODES = ("a", "b")\nclass C:\n    def __init__(self, m, n):\n        if m not in ("x", "y"):\n            raise E\n'
    old += "        if n not in MODES:\n            raise E\n        if n not in (1, 2):\n            raise E\n"
    old += "        if m in ('x',):\n            pass\n        for k in n:\n            if k not in MODES:\n                raise E\n"
    assert _hand_checked_choices(ast.parse(old)) == [4, 6]


def test_check_choices_reads_the_constructors_literal():
    def f(fusion: Literal["add", "concat"] = "add", stride: Literal[4, 8] = 4, free: str = "x"):
        pass

    check_choices(f, "f", fusion="concat", stride=8)
    with pytest.raises(ValueError, match=r"^f fusion must be 'add' or 'concat', got 'ad'; did you mean 'add'\?$"):
        check_choices(f, "f", fusion="ad")
    with pytest.raises(ValueError, match=r"^f stride must be 4 or 8, got True$"):
        check_choices(f, "f", stride=True)  # a bool is not the int 1 of a Literal, nor any other choice
    with pytest.raises(ValueError, match=r"^f stride must be 4 or 8, got 4.0$"):
        check_choices(f, "f", stride=4.0)
    with pytest.raises(TypeError, match="not annotated with a Literal"):
        check_choices(f, "f", free="y")
