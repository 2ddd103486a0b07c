"""The wire, checked: the client's models and errors against the HTTP contract,
``api/openapi.yaml`` (read from the repository; no server needed).

The rules, for every dataclass in :mod:`precond_client.models` ("field": the dataclass's;
"property": the schema's):

1. **It names what it mirrors.** ``SCHEMA`` is the schema (or a tuple of schemas, when one class
   reads several, e.g. ``PlannedTrajectory`` for a plan's and a proposal's trajectory); every
   named schema exists, and no schema is mirrored by two classes.
2. **Same names.** Its fields, except those marked ``CLIENT_ONLY`` (``raw``, a header's
   ``replayed``), are exactly the properties of its schemas (``allOf`` merged; the union when it
   mirrors several). ``COLUMNS`` names an array property whose items' properties are fields of
   their own (``Precondition`` reads ``results`` column by column).
3. **Omitted means defaulted.** A property the server always sends (``required`` in every schema
   the class mirrors) is a field without a default: the client cannot be built without it, so
   a renamed or dropped key fails loudly instead of turning into ``None``. A property some
   mirrored schema leaves out of ``required`` (the server may omit it; a request may leave it
   out) is a field with the default ``None``.
4. **Null means Optional.** A field's type admits ``None`` exactly when the server may send
   ``null`` for it (``type: [..., 'null']``, a ``null`` branch of ``oneOf``/``anyOf``) or omit it.
5. **Nested models match nested schemas.** A property that refers to a schema a client class
   mirrors (directly, through ``allOf``/``oneOf``/``anyOf`` or as array items) is a field of
   that class (or a list of it, or Optional), and a field typed with a client class refers to a
   schema that class mirrors.
6. **The spec's examples read back.** Every example of a response whose schema a class mirrors
   is read by its ``from_json`` into the values the example shows.

And for the errors: the codes :mod:`precond_client.errors` maps are exactly the spec's
``ErrorBody.code`` enum (the one list of codes; the server's Rust test checks it against the
codes the server produces), each to its own subclass of ``ApiError``; every error example in the
spec is read into the class of its code.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Iterator, Mapping
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from precond_client import errors, models

SPEC_PATH = Path(__file__).resolve().parents[3] / "api" / "openapi.yaml"

Schema = dict[str, Any]


@cache
def spec() -> dict[str, Any]:
    loaded = yaml.safe_load(SPEC_PATH.read_text(encoding="utf-8"))
    assert isinstance(loaded, dict)
    return loaded


def schemas() -> dict[str, Schema]:
    found = spec()["components"]["schemas"]
    assert isinstance(found, dict)
    return found


def ref_name(ref: str) -> str:
    prefix = "#/components/schemas/"
    assert ref.startswith(prefix), ref
    return ref[len(prefix) :]


def merged(name: str) -> tuple[dict[str, Schema], set[str]]:
    """A named schema's properties and required names, its ``allOf`` parts merged."""
    props: dict[str, Schema] = {}
    required: set[str] = set()

    def walk(s: Schema) -> None:
        if "$ref" in s:
            walk(schemas()[ref_name(s["$ref"])])
        for part in s.get("allOf", []):
            walk(part)
        props.update(s.get("properties", {}))
        required.update(s.get("required", []))

    walk(schemas()[name])
    return props, required


def refs(prop: Schema) -> set[str]:
    """The schemas a property refers to: directly, through ``allOf``/``oneOf``/``anyOf`` and
    as array items (not what those schemas refer to in turn)."""
    out: set[str] = set()
    if "$ref" in prop:
        out.add(ref_name(prop["$ref"]))
    for key in ("allOf", "oneOf", "anyOf"):
        for part in prop.get(key, []):
            out |= refs(part)
    if isinstance(prop.get("items"), dict):
        out |= refs(prop["items"])
    return out


def nullable(prop: Schema) -> bool:
    """Whether a property's value may be ``null``."""
    t = prop.get("type")
    if t == "null" or (isinstance(t, list) and "null" in t):
        return True
    if "const" in prop and prop["const"] is None:
        return True
    return any(nullable(part) for key in ("oneOf", "anyOf") for part in prop.get(key, []))


# ---------------------------------------------------------------- the client's side


def mirrored(cls: type) -> tuple[str, ...]:
    named = cls.__dict__.get("SCHEMA")
    if named is None:
        return ()
    return (named,) if isinstance(named, str) else tuple(named)


def model_classes() -> list[type]:
    """Every dataclass defined in ``precond_client.models``."""
    return [
        obj
        for obj in vars(models).values()
        if isinstance(obj, type)
        and dataclasses.is_dataclass(obj)
        and obj.__module__ == models.__name__
    ]


def by_schema() -> dict[str, type]:
    out: dict[str, type] = {}
    for cls in model_classes():
        for name in mirrored(cls):
            assert name not in out, f"{name} is mirrored by {out[name].__name__} and {cls.__name__}"
            out[name] = cls
    return out


def wire_fields(cls: type) -> dict[str, dataclasses.Field[Any]]:
    return {
        f.name: f
        for f in dataclasses.fields(cls)
        if not models.CLIENT_ONLY.items() <= f.metadata.items()
    }


def admits_none(tp: Any) -> bool:
    return tp is type(None) or (
        typing.get_origin(tp) in (typing.Union, types.UnionType)
        and type(None) in typing.get_args(tp)
    )


def client_classes_in(tp: Any) -> set[type]:
    """The client dataclasses a field's type names (through unions and lists)."""
    found = {tp} if isinstance(tp, type) and tp in model_classes() else set()
    for arg in typing.get_args(tp):
        found |= client_classes_in(arg)
    return found


class Expected(typing.NamedTuple):
    """What the spec says about one field of a class."""

    always_sent: bool
    may_be_null: bool
    refers_to: set[str]


def expected_fields(cls: type) -> dict[str, Expected]:
    """The fields the spec asks of ``cls``, by rules 2 to 5."""
    names = mirrored(cls)
    columns: Mapping[str, str] = getattr(cls, "COLUMNS", {})
    merged_all = [merged(n) for n in names]
    out: dict[str, Expected] = {}
    for prop_name in sorted({p for props, _ in merged_all for p in props}):
        in_every = all(prop_name in props for props, _ in merged_all)
        always = in_every and all(prop_name in req for _, req in merged_all)
        prop = next(props[prop_name] for props, _ in merged_all if prop_name in props)
        if prop_name in columns:
            assert prop.get("type") == "array", f"{cls.__name__}.COLUMNS: {prop_name} is no array"
            assert refs(prop) == {columns[prop_name]}, f"{prop_name} items: {refs(prop)}"
            item_props, item_required = merged(columns[prop_name])
            for col, col_prop in item_props.items():
                out[col] = Expected(
                    always and col in item_required, nullable(col_prop), refs(col_prop)
                )
            continue
        out[prop_name] = Expected(always, nullable(prop), refs(prop))
    return out


MODEL_CLASSES = model_classes()


def test_every_model_names_schemas_that_exist() -> None:
    assert len(MODEL_CLASSES) >= 10
    for cls in MODEL_CLASSES:
        names = mirrored(cls)
        assert names, f"models.{cls.__name__} names no SCHEMA it mirrors"
        for name in names:
            assert name in schemas(), f"models.{cls.__name__}.SCHEMA: no schema {name} in the spec"
    by_schema()  # no schema mirrored twice


@pytest.mark.parametrize("cls", MODEL_CLASSES, ids=lambda c: c.__name__)
def test_model_fields_are_the_schema_properties(cls: type) -> None:
    expected = expected_fields(cls)
    fields = wire_fields(cls)
    where = f"models.{cls.__name__} (schema {', '.join(mirrored(cls))})"
    missing = sorted(set(expected) - set(fields))
    extra = sorted(set(fields) - set(expected))
    assert not missing, f"{where} lacks the properties {missing}"
    assert not extra, f"{where} has fields the spec does not know: {extra} (CLIENT_ONLY?)"

    hints = typing.get_type_hints(cls, vars(models))
    known = by_schema()
    for name, exp in expected.items():
        f, tp = fields[name], hints[name]
        has_default = (
            f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING
        )
        if exp.always_sent:
            assert not has_default, f"{where}.{name} is required in the spec: it takes no default"
        else:
            assert has_default and f.default is None, (
                f"{where}.{name} may be omitted (not required): it defaults to None"
            )
        may_be_none = exp.may_be_null or not exp.always_sent
        assert admits_none(tp) == may_be_none, (
            f"{where}.{name}: its type {tp} must {'' if may_be_none else 'not '}admit None "
            f"(the spec: {'nullable' if exp.may_be_null else 'not nullable'}, "
            f"{'required' if exp.always_sent else 'optional'})"
        )
        mirrored_refs = {r for r in exp.refers_to if r in known}
        named = client_classes_in(tp)
        assert {known[r] for r in mirrored_refs} <= named, (
            f"{where}.{name} refers to {sorted(mirrored_refs)}: its type {tp} must use "
            f"{sorted(known[r].__name__ for r in mirrored_refs)}"
        )
        for inner in named:
            assert set(mirrored(inner)) & exp.refers_to, (
                f"{where}.{name} is typed {inner.__name__} (schema {mirrored(inner)}), but the "
                f"property refers to {sorted(exp.refers_to) or 'no schema'}"
            )


# ---------------------------------------------------------------- rule 6: examples read back


def response_examples() -> Iterator[tuple[str, str, Any]]:
    """``(where, schema, value)`` of every example of a JSON response with a named schema, and
    of the objects in it that have a named schema of their own (a list's ``items``)."""
    for path, item in spec()["paths"].items():
        for method, op in item.items():
            if not isinstance(op, dict):
                continue
            for status, response in op.get("responses", {}).items():
                content = response.get("content", {}).get("application/json", {})
                ref = content.get("schema", {}).get("$ref")
                if ref is None:
                    continue
                for ex_name, ex in content.get("examples", {}).items():
                    if "$ref" in ex:
                        ex = spec()["components"]["examples"][ex["$ref"].rsplit("/", 1)[-1]]
                    where = f"{method.upper()} {path} {status} {ex_name}"
                    yield from within(where, ref_name(ref), ex["value"])


def within(where: str, schema: str, value: Any) -> Iterator[tuple[str, str, Any]]:
    yield where, schema, value
    if schema in by_schema() or not isinstance(value, dict):
        return
    props, _ = merged(schema)
    for key, prop in props.items():
        inner = refs(prop)
        if len(inner) != 1 or key not in value:
            continue
        (name,) = inner
        items = value[key] if isinstance(value[key], list) else [value[key]]
        for i, v in enumerate(items):
            yield from within(f"{where}.{key}[{i}]", name, v)


def as_json(obj: Any) -> Any:
    """A read model back in its JSON form (arrays as lists), to compare with the example."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        out = {
            name: as_json(getattr(obj, name))
            for name in wire_fields(type(obj))
            if getattr(obj, name) is not None
        }
        for prop, item in getattr(type(obj), "COLUMNS", {}).items():
            cols = {name: out.pop(name) for name in merged(item)[0]}
            rows = zip(*cols.values(), strict=True)
            out[prop] = [dict(zip(cols, row, strict=True)) for row in rows]
        return out
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, list):
        return [as_json(x) for x in obj]
    return obj


def same(read: Any, shown: Any, path: str) -> None:
    if isinstance(shown, dict):
        assert isinstance(read, dict), f"{path}: read {read!r}, the example shows {shown!r}"
        for key, value in shown.items():
            if value is None:
                assert read.get(key) is None, f"{path}.{key}: read {read.get(key)!r}, not null"
            elif key in read:
                same(read[key], value, f"{path}.{key}")
    elif isinstance(shown, list):
        assert isinstance(read, list) and len(read) == len(shown), f"{path}: {read!r}"
        for i, (r, s) in enumerate(zip(read, shown, strict=True)):
            same(r, s, f"{path}[{i}]")
    elif isinstance(shown, (int, float)) and not isinstance(shown, bool):
        assert read == pytest.approx(shown), f"{path}: read {read!r}, the example shows {shown!r}"
    else:
        assert read == shown, f"{path}: read {read!r}, the example shows {shown!r}"


def test_every_response_example_of_a_mirrored_schema_reads_back() -> None:
    known = by_schema()
    read = 0
    for where, schema, value in response_examples():
        cls = known.get(schema)
        if cls is None:
            continue
        obj = typing.cast(Any, cls).from_json(value)
        back = as_json(obj)
        # Every property the example shows is a field that was read into the same value.
        expected = expected_fields(cls)
        columns = getattr(cls, "COLUMNS", {})
        for key in value:
            assert key in expected or key in columns, f"{where}: {key} is not read"
        same(back, value, f"{where} ({cls.__name__})")
        read += 1
    assert read >= 10, "the spec's examples of experiments, proposals, models, ... were read"


# ---------------------------------------------------------------- errors


def spec_error_codes() -> list[str]:
    code = schemas()["ErrorBody"]["properties"]["code"]
    assert "enum" in code, "ErrorBody.code enumerates the codes"
    return list(code["enum"])


def test_every_error_code_has_its_own_exception_class() -> None:
    codes = spec_error_codes()
    mapped = errors._BY_CODE
    assert len(codes) == len(set(codes)) >= 17
    assert sorted(mapped) == sorted(codes), (
        f"not mapped: {sorted(set(codes) - set(mapped))}; "
        f"not in the spec: {sorted(set(mapped) - set(codes))}"
    )
    classes = list(mapped.values())
    assert len(set(classes)) == len(classes), "each code has a class of its own"
    for code, cls in mapped.items():
        assert issubclass(cls, errors.ApiError) and cls is not errors.ApiError, code
        assert f"``{code}``" in (cls.__doc__ or "") or f" {code}``" in (cls.__doc__ or ""), (
            f"{cls.__name__}'s docstring names its code {code}"
        )
        raised = errors.from_response(400, {"error": {"code": code, "message": "m"}})
        assert type(raised) is cls and raised.code == code


def error_examples() -> Iterator[tuple[str, dict[str, Any]]]:
    """Every example in the spec whose value is an error body."""

    def walk(node: Any, where: str) -> Iterator[tuple[str, dict[str, Any]]]:
        if isinstance(node, dict):
            value = node.get("value")
            if isinstance(value, dict) and isinstance(value.get("error"), dict):
                yield where, value
            for key, child in node.items():
                yield from walk(child, f"{where}/{key}")
        elif isinstance(node, list):
            for i, child in enumerate(node):
                yield from walk(child, f"{where}[{i}]")

    yield from walk(spec(), "")


def test_every_error_example_is_read_into_the_class_of_its_code() -> None:
    seen = set()
    for where, body in error_examples():
        code = body["error"]["code"]
        assert code in spec_error_codes(), f"{where}: {code} is not in ErrorBody.code"
        raised = errors.from_response(400, body)
        assert type(raised) is errors._BY_CODE[code], where
        assert raised.message == body["error"]["message"]
        seen.add(code)
    assert len(seen) >= 12


def test_the_start_at_the_goal_is_recognised_from_the_spec_example() -> None:
    proposals = spec()["paths"]["/v1/experiments/{id}/proposals"]["post"]
    examples = proposals["responses"]["422"]["content"]["application/json"]["examples"]
    at_goal = errors.from_response(422, examples["at_goal"]["value"])
    assert isinstance(at_goal, errors.ValidationFailed) and at_goal.start_satisfies_goal
    outside = errors.from_response(422, examples["goal_outside"]["value"])
    assert isinstance(outside, errors.ValidationFailed) and not outside.start_satisfies_goal


def test_request_models_send_the_schema_properties() -> None:
    full = models.Transition(
        [0.0, 0.0], [0.1, 0.0], [0.1, 0.0], s_pred=[0.1, 0.0], predictions={"mine": [0.1, 0.0]}
    ).to_json()
    assert set(full) == set(expected_fields(models.Transition))
    bare = models.Transition([0.0, 0.0], [0.1, 0.0], [0.1, 0.0]).to_json()
    _, required = merged("TransitionRequest")
    assert set(bare) == required
    candidate = models.Candidate([[0.0, 0.0], [0.1, 0.0]], [[0.1, 0.0]]).to_json()
    assert set(candidate) == set(expected_fields(models.Candidate))
