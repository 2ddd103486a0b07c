//! The bodies `crates/precond/src/api.rs` sends and reads (with the types they embed) and the component schemas
//! of `api/openapi.yaml` describe the same JSON.
//!
//! Each wire type derives `schemars::JsonSchema` (schemars 1.x: JSON Schema generated from the
//! serde attributes, so it knows `rename`, `flatten`, `tag`, `default`, `deny_unknown_fields`
//! and `skip_serializing_if` as serde applies them). `ENTRIES` (`precond_tools::openapi::
//! registry`, the table `precond openapi` generates the document's schemas from) maps every
//! spec schema to the Rust type of the same body, with the side of the wire it describes:
//! - a **response** is generated for serialisation: a property is required when the server
//!   always emits it (an `Option` included, unless it is skipped when `None`);
//! - a **request** is generated for deserialisation: a property is required when the server
//!   refuses a body without it.
//!
//! Both schemas are reduced to the same plain form ([`Node`]: `$ref`s resolved, `allOf` merged,
//! `oneOf`/`anyOf` as unions, a union of objects told apart by a constant property as a tagged
//! union, `type` lists and `enum`/`const` as sets of kinds and values) and compared both ways,
//! recursively, so a field added or dropped at any depth fails. The rules, mirroring
//! `clients/python/tests/test_wire.py`:
//! 1. **Same names.** Every object has the same property names; a tagged union (`DomainSpec`,
//!    `ModelSpec`, tag `kind`) has the same tag values, each variant compared with the spec's
//!    `oneOf` member of that value.
//! 2. **Same `required`.** Responses: the spec requires exactly what the server always emits.
//!    Requests: the spec requires exactly what the server requires; `additionalProperties:
//!    false` exactly where the server refuses unknown fields (`deny_unknown_fields`).
//! 3. **Null where null is sent.** A response property is nullable in the spec exactly when the
//!    server may send `null` (an `Option` it does not skip). A request property the spec lets be
//!    `null` is an `Option` (the server may also read `null` for a property the spec does not
//!    offer it for: serde reads `null` as absent for every `Option`).
//! 4. **Same kinds and values.** Boolean, integer, number, string, array or object alike; string
//!    enums (strategy, aggregation, kernel, noise, preset, statuses, …) with the same values. A
//!    Rust `String` may be documented as an enum or a `const` (`Health.status`, `Diagnostics.
//!    method`): the spec says which strings the server puts there.
//! 5. **Nothing unchecked.** Every schema of `components/schemas` is in `ENTRIES`, checked as
//!    part of one ([`REACHED`]) or in the commented [`NOT_TYPED`] list.
//!
//! A serde `serde_json::Value` (an error's `details`) is unconstrained on the Rust side and is not
//! compared further.
//!
//! The schemas are generated from these types (`generated.rs` checks the document is what they
//! generate); this comparison reads both independently of the generator, so a generator that
//! got a rule wrong — a nullable property, a required one, a variant — fails here.

use schemars::JsonSchema;
use serde_json::{Map, Value};
use std::cell::RefCell;
use std::collections::{BTreeMap, BTreeSet};

use precond::api;
use precond_tools::openapi::registry::{Adjust, ENTRIES, Entry, Side, rust_schema};

// ---------------------------------------------------------------- the table

/// The adjustments [`CONTEXTS`] implies for the bodies that embed a schema it names: a
/// proposal's trajectory always has its acquisition values, a plan's never.
const NESTED: &[(&str, Adjust)] = &[
    (
        "ContinueResponse",
        Adjust::Require("proposal.trajectory", &["alpha_step", "alpha"]),
    ),
    (
        "Proposal",
        Adjust::Require("trajectory", &["alpha_step", "alpha"]),
    ),
    ("Plan", Adjust::Omit("trajectory", &["alpha_step", "alpha"])),
];

/// Spec schemas without a Rust type of their own, compared as parts of [`ENTRIES`] bodies (the
/// test checks that each is reached from one).
const REACHED: &[&str] = &[
    // the variants of DomainSpec and ResolvedDomainSpec (settings::DomainSpec)
    "IcyGridworldSpec",
    "KinematicSpec",
    "WaterPlantSpec",
    "CustomSpec",
    "ResolvedIcyGridworldSpec",
    "ResolvedKinematicSpec",
    "ResolvedCustomSpec",
    // the variants of ModelSpec and ResolvedModelSpec (settings::ModelSpec)
    "RemoteModelSpec",
    "LinearModelSpec",
    "ClientModelSpec",
    "ResolvedRemoteModelSpec",
    "ResolvedLinearModelSpec",
    // the variants of FeatureMap and NoisePredictor (a model export's)
    "UnitBoxFeatureMap",
    "KinematicPredictionFeatureMap",
    "PerMoveFeatureMap",
    "ActionAndRotationFeatureMap",
    "HomoscedasticNoise",
    "HeteroscedasticNoise",
];

/// Spec schemas no Rust type describes, each with the reason.
const NOT_TYPED: &[(&str, &str)] = &[
    // What the error details below hold for a state or a goal.
    ("Vector", "a JSON value"),
    // An error's `details`: a JSON value each error builds in `ApiError::details`
    // (crates/precond/src/http/error.rs); the codes are checked against the spec in contract.rs.
    ("RetryDetails", "a JSON value"),
    ("DeadlineDetails", "a JSON value"),
    ("LeaseDetails", "a JSON value"),
    ("ModelErrorDetails", "a JSON value"),
    ("ValidationDetails", "a JSON value"),
    ("PayloadTooLargeDetails", "a JSON value"),
    ("NoPlanDetails", "a JSON value"),
    ("StoredPrefixDetails", "a JSON value"),
    ("ImportStoppedDetails", "a JSON value"),
    // `Error` narrowed to one code, for the responses that answer only that code.
    ("ValidationError", "Error with one code"),
    ("NoPlanError", "Error with one code"),
    ("PayloadTooLargeError", "Error with one code"),
];

/// A route's query string and the Rust type it is read into (compared like a request body
/// with the spec's `in: query` parameters: the same names, `required` alike, the same kinds).
struct Query {
    method: &'static str,
    path: &'static str,
    rust: fn() -> &'static str,
    generate: fn(Side) -> Value,
}

const fn query<T: JsonSchema>(method: &'static str, path: &'static str) -> Query {
    Query {
        method,
        path,
        rust: std::any::type_name::<T>,
        generate: rust_schema::<T>,
    }
}

/// Every route that reads a query string.
const QUERIES: &[Query] = &[
    query::<api::ExperimentsQuery>("get", "/v1/experiments"),
    query::<api::TransitionsQuery>("get", "/v1/experiments/{id}/transitions"),
    query::<api::ImportQuery>("post", "/v1/experiments/{id}/imports"),
    query::<api::PageQuery>("get", "/v1/experiments/{id}/runs"),
    query::<api::PageQuery>("get", "/v1/experiments/{id}/exclusions"),
    query::<api::DiagnosticsQuery>("get", "/v1/experiments/{id}/model/diagnostics"),
    query::<api::ExportQuery>("get", "/v1/experiments/{id}/model/export"),
    query::<api::PointQuery>("get", "/v1/experiments/{id}/precondition"),
    query::<api::MapQuery>("get", "/v1/experiments/{id}/precondition/map"),
];

// ---------------------------------------------------------------- the two documents

/// A type's name without the crate: `api::ExperimentResponse`.
fn short(type_name: &str) -> &str {
    type_name.strip_prefix("precond::").unwrap_or(type_name)
}

fn spec() -> Value {
    let text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../api/openapi.yaml"
    ))
    .expect("api/openapi.yaml exists");
    let yaml: serde_yaml::Value = serde_yaml::from_str(&text).expect("api/openapi.yaml is YAML");
    serde_json::to_value(yaml).expect("the spec is JSON-compatible")
}

/// A JSON Schema document: where its `$ref`s point, and which of them were followed.
struct Doc<'a> {
    defs: &'a Map<String, Value>,
    prefix: &'static str,
    followed: RefCell<BTreeSet<String>>,
}

impl<'a> Doc<'a> {
    fn new(defs: &'a Map<String, Value>, prefix: &'static str) -> Self {
        Self {
            defs,
            prefix,
            followed: RefCell::default(),
        }
    }

    fn resolve(&self, reference: &str) -> &'a Value {
        let name = reference
            .strip_prefix(self.prefix)
            .unwrap_or_else(|| panic!("{reference}: not under {}", self.prefix));
        self.followed.borrow_mut().insert(name.to_string());
        self.defs
            .get(name)
            .unwrap_or_else(|| panic!("{reference}: no such schema"))
    }
}

// ---------------------------------------------------------------- the plain form

/// What a schema admits, kind by kind.
#[derive(Clone, Debug, Default)]
struct Node {
    /// No constraint on the kind (no `type`, `enum`, `const` or alternatives); `object` may
    /// still constrain objects (`{required: [...]}` in an `allOf`).
    any: bool,
    null: bool,
    boolean: bool,
    integer: bool,
    number: bool,
    string: Option<Strings>,
    array: Option<Box<Node>>,
    object: Option<Objects>,
}

#[derive(Clone, Debug, PartialEq)]
enum Strings {
    Any,
    Of(BTreeSet<String>),
}

#[derive(Clone, Debug)]
enum Objects {
    One(Obj),
    /// Objects told apart by the constant string of property `tag`.
    Tagged {
        tag: String,
        variants: BTreeMap<String, Obj>,
    },
    /// Objects with nothing to tell them apart by.
    Untagged(Vec<Obj>),
}

#[derive(Clone, Debug, Default)]
struct Obj {
    props: BTreeMap<String, Node>,
    required: BTreeSet<String>,
    /// `additionalProperties: false`.
    closed: bool,
}

impl Node {
    fn any() -> Self {
        Self {
            any: true,
            ..Self::default()
        }
    }

    fn describe(&self) -> String {
        if self.any {
            return "anything".into();
        }
        let mut kinds = Vec::new();
        if self.null {
            kinds.push("null".to_string());
        }
        if self.boolean {
            kinds.push("boolean".into());
        }
        if self.integer {
            kinds.push("integer".into());
        }
        if self.number {
            kinds.push("number".into());
        }
        match &self.string {
            Some(Strings::Any) => kinds.push("string".into()),
            Some(Strings::Of(v)) => kinds.push(format!("string {v:?}")),
            None => {}
        }
        if self.array.is_some() {
            kinds.push("array".into());
        }
        match &self.object {
            Some(Objects::Tagged { tag, .. }) => kinds.push(format!("object tagged by {tag}")),
            Some(_) => kinds.push("object".into()),
            None => {}
        }
        kinds.join(" | ")
    }

    /// The object it admits, when it admits objects of one shape.
    fn obj_mut(&mut self) -> Option<&mut Obj> {
        match &mut self.object {
            Some(Objects::One(o)) => Some(o),
            _ => None,
        }
    }
}

fn str_set(values: impl IntoIterator<Item = String>) -> Strings {
    Strings::Of(values.into_iter().collect())
}

impl Doc<'_> {
    /// The plain form of a schema.
    fn node(&self, schema: &Value) -> Node {
        let map = match schema {
            Value::Bool(true) => return Node::any(),
            Value::Object(map) => map,
            other => panic!("not a schema: {other}"),
        };
        let mut node = own_keywords(map, self);
        if let Some(Value::String(r)) = map.get("$ref") {
            node = intersect(node, self.node(self.resolve(r)));
        }
        for part in map
            .get("allOf")
            .and_then(Value::as_array)
            .into_iter()
            .flatten()
        {
            node = intersect(node, self.node(part));
        }
        for key in ["oneOf", "anyOf"] {
            if let Some(alternatives) = map.get(key).and_then(Value::as_array) {
                let tag = map
                    .get("discriminator")
                    .and_then(|d| d.get("propertyName"))
                    .and_then(Value::as_str);
                let alts = alternatives.iter().map(|a| self.node(a)).collect();
                node = intersect(node, union(alts, tag));
            }
        }
        node
    }
}

/// The kinds a schema's own keywords (`type`, `enum`, `const`, `properties`, `required`,
/// `items`, `additionalProperties`) admit.
fn own_keywords(map: &Map<String, Value>, doc: &Doc) -> Node {
    let obj = || Obj {
        props: map
            .get("properties")
            .and_then(Value::as_object)
            .into_iter()
            .flatten()
            .map(|(k, v)| (k.clone(), doc.node(v)))
            .collect(),
        required: map
            .get("required")
            .and_then(Value::as_array)
            .into_iter()
            .flatten()
            .map(|v| v.as_str().expect("required names").to_string())
            .collect(),
        closed: map.get("additionalProperties") == Some(&Value::Bool(false)),
    };
    let values: Option<Vec<&Value>> = match (map.get("enum"), map.get("const")) {
        (Some(Value::Array(e)), _) => Some(e.iter().collect()),
        (_, Some(c)) => Some(vec![c]),
        _ => None,
    };
    let types: Option<Vec<&str>> = match map.get("type") {
        Some(Value::String(t)) => Some(vec![t.as_str()]),
        Some(Value::Array(ts)) => Some(ts.iter().map(|t| t.as_str().unwrap()).collect()),
        _ => None,
    };
    let mut node = Node::default();
    match (types, values) {
        (Some(types), values) => {
            for t in types {
                match t {
                    "null" => node.null = true,
                    "boolean" => node.boolean = true,
                    "integer" => node.integer = true,
                    "number" => node.number = true,
                    "string" => node.string = Some(Strings::Any),
                    "array" => {
                        let items = map.get("items").map_or_else(Node::any, |i| doc.node(i));
                        node.array = Some(Box::new(items));
                    }
                    "object" => node.object = Some(Objects::One(obj())),
                    other => panic!("unknown type {other}"),
                }
            }
            if let Some(values) = values {
                let strings: Vec<String> = values
                    .iter()
                    .filter_map(|v| v.as_str().map(str::to_string))
                    .collect();
                if node.string.is_some() {
                    node.string = Some(str_set(strings));
                }
                node.null &= values.iter().any(|v| v.is_null());
            }
        }
        (None, Some(values)) => {
            for v in values {
                match v {
                    Value::Null => node.null = true,
                    Value::String(s) => {
                        let mut set = match node.string.take() {
                            Some(Strings::Of(set)) => set,
                            _ => BTreeSet::new(),
                        };
                        set.insert(s.clone());
                        node.string = Some(Strings::Of(set));
                    }
                    Value::Bool(_) => node.boolean = true,
                    Value::Number(n) if n.is_f64() => node.number = true,
                    Value::Number(_) => node.integer = true,
                    other => panic!("enum value {other} is not compared"),
                }
            }
        }
        (None, None) => {
            node.any = true;
            if ["properties", "required", "additionalProperties"]
                .iter()
                .any(|k| map.contains_key(*k))
            {
                node.object = Some(Objects::One(obj()));
            }
        }
    }
    node
}

/// What both admit (`allOf`).
fn intersect(a: Node, b: Node) -> Node {
    match (a.any, b.any) {
        (true, true) => Node {
            any: true,
            object: merge_refinements(a.object, b.object),
            ..Node::default()
        },
        (true, false) => refine(b, a.object),
        (false, true) => refine(a, b.object),
        (false, false) => Node {
            any: false,
            null: a.null && b.null,
            boolean: a.boolean && b.boolean,
            // `integer` is within `number`.
            integer: (a.integer && (b.integer || b.number)) || (b.integer && a.number),
            number: a.number && b.number,
            string: match (a.string, b.string) {
                (Some(Strings::Any), s) | (s, Some(Strings::Any)) => s,
                (Some(Strings::Of(x)), Some(Strings::Of(y))) => {
                    Some(Strings::Of(x.intersection(&y).cloned().collect()))
                }
                _ => None,
            },
            array: match (a.array, b.array) {
                (Some(x), Some(y)) => Some(Box::new(intersect(*x, *y))),
                _ => None,
            },
            object: match (a.object, b.object) {
                (Some(x), Some(y)) => Some(intersect_objects(x, y)),
                _ => None,
            },
        },
    }
}

fn refine(mut node: Node, refinement: Option<Objects>) -> Node {
    if let Some(r) = refinement {
        node.object = node.object.map(|objects| intersect_objects(objects, r));
    }
    node
}

fn merge_refinements(a: Option<Objects>, b: Option<Objects>) -> Option<Objects> {
    match (a, b) {
        (Some(x), Some(y)) => Some(intersect_objects(x, y)),
        (x, None) => x,
        (None, y) => y,
    }
}

fn merge_obj(mut a: Obj, b: Obj) -> Obj {
    for (name, node) in b.props {
        let merged = match a.props.remove(&name) {
            Some(mine) => intersect(mine, node),
            None => node,
        };
        a.props.insert(name, merged);
    }
    a.required.extend(b.required);
    a.closed |= b.closed;
    a
}

fn intersect_objects(a: Objects, b: Objects) -> Objects {
    match (a, b) {
        (Objects::One(x), Objects::One(y)) => Objects::One(merge_obj(x, y)),
        (Objects::Tagged { tag, variants }, Objects::One(o))
        | (Objects::One(o), Objects::Tagged { tag, variants }) => Objects::Tagged {
            tag,
            variants: variants
                .into_iter()
                .map(|(k, v)| (k, merge_obj(v, o.clone())))
                .collect(),
        },
        (
            Objects::Tagged { tag, variants },
            Objects::Tagged {
                tag: tag2,
                variants: mut variants2,
            },
        ) => {
            assert_eq!(tag, tag2, "allOf of unions tagged by different properties");
            Objects::Tagged {
                tag,
                variants: variants
                    .into_iter()
                    .filter_map(|(k, v)| variants2.remove(&k).map(|w| (k, merge_obj(v, w))))
                    .collect(),
            }
        }
        (Objects::Untagged(list), Objects::One(o)) | (Objects::One(o), Objects::Untagged(list)) => {
            Objects::Untagged(list.into_iter().map(|v| merge_obj(v, o.clone())).collect())
        }
        (x, y) => panic!("allOf of {x:?} and {y:?} is not compared"),
    }
}

/// What either admits (`oneOf`, `anyOf`); objects become a union tagged by `tag` (the
/// discriminator) or by the one property every alternative holds a constant string in.
fn union(alternatives: Vec<Node>, tag: Option<&str>) -> Node {
    if alternatives.iter().any(|a| a.any && a.object.is_none()) {
        return Node::any();
    }
    let mut node = Node::default();
    let mut objects = Vec::new();
    let mut arrays = Vec::new();
    for a in alternatives {
        node.null |= a.null;
        node.boolean |= a.boolean;
        node.integer |= a.integer;
        node.number |= a.number;
        node.string = match (node.string.take(), a.string) {
            (None, s) | (s, None) => s,
            (Some(Strings::Of(mut x)), Some(Strings::Of(y))) => {
                x.extend(y);
                Some(Strings::Of(x))
            }
            _ => Some(Strings::Any),
        };
        if let Some(items) = a.array {
            arrays.push(*items);
        }
        match a.object {
            Some(Objects::One(o)) => objects.push(o),
            Some(Objects::Tagged { variants, .. }) => objects.extend(variants.into_values()),
            Some(Objects::Untagged(list)) => objects.extend(list),
            None => {}
        }
    }
    node.array = match arrays.len() {
        0 => None,
        1 => Some(Box::new(arrays.pop().unwrap())),
        _ => panic!("a union of several array kinds is not compared"),
    };
    node.object = match objects.len() {
        0 => None,
        1 => Some(Objects::One(objects.pop().unwrap())),
        _ => Some(tagged(objects, tag)),
    };
    node
}

fn constant(node: &Node) -> Option<&str> {
    match &node.string {
        Some(Strings::Of(v)) if v.len() == 1 && !node.null => v.iter().next().map(String::as_str),
        _ => None,
    }
}

fn tagged(objects: Vec<Obj>, tag: Option<&str>) -> Objects {
    let candidates: Vec<String> = match tag {
        Some(t) => vec![t.to_string()],
        None => objects[0].props.keys().cloned().collect(),
    };
    for tag in candidates {
        let values: Option<Vec<String>> = objects
            .iter()
            .map(|o| o.props.get(&tag).and_then(constant).map(str::to_string))
            .collect();
        if let Some(values) = values {
            let distinct: BTreeSet<&String> = values.iter().collect();
            if distinct.len() == objects.len() {
                let variants = values.into_iter().zip(objects).collect();
                return Objects::Tagged { tag, variants };
            }
        }
    }
    Objects::Untagged(objects)
}

// ---------------------------------------------------------------- adjustments

fn at_path<'n>(node: &'n mut Node, path: &str, what: &str) -> &'n mut Obj {
    let mut here = node;
    for step in path.split('.').filter(|s| !s.is_empty()) {
        here = here
            .obj_mut()
            .and_then(|o| o.props.get_mut(step))
            .unwrap_or_else(|| panic!("{what}: no property {step} on the way to {path:?}"));
    }
    here.obj_mut()
        .unwrap_or_else(|| panic!("{what}: {path:?} is not one object"))
}

fn apply(node: &mut Node, adjust: &Adjust, what: &str) {
    match *adjust {
        Adjust::Require(path, names) => {
            let obj = at_path(node, path, what);
            for name in names {
                assert!(
                    obj.props.contains_key(*name) && !obj.required.contains(*name),
                    "{what}: Require {path}.{name}: the type must have it as an optional \
                     property (else drop the adjustment)"
                );
                obj.required.insert(name.to_string());
                obj.props.get_mut(*name).unwrap().null = false;
            }
        }
        Adjust::Omit(path, names) => {
            let obj = at_path(node, path, what);
            for name in names {
                assert!(
                    obj.props.contains_key(*name) && !obj.required.contains(*name),
                    "{what}: Omit {path}.{name}: the type must have it as an optional property \
                     (else drop the adjustment)"
                );
                obj.props.remove(*name);
            }
        }
    }
}

// ---------------------------------------------------------------- the comparison

struct Compare {
    side: Side,
    /// How a problem at the top is named: `(body)` or `(query)`.
    root: &'static str,
    problems: Vec<String>,
}

impl Compare {
    fn problem(&mut self, path: &str, what: String) {
        let path = if path.is_empty() { self.root } else { path };
        self.problems.push(format!("{path}: {what}"));
    }

    /// `rust` is the server's schema of the value at `path`, `spec` the spec's.
    fn node(&mut self, path: &str, rust: &Node, spec: &Node) {
        if rust.any && rust.object.is_none() {
            return; // a `serde_json::Value`: the spec says what the server puts there
        }
        if spec.any {
            self.problem(
                path,
                format!(
                    "the spec does not say what it is; the server: {}",
                    rust.describe()
                ),
            );
            return;
        }
        match self.side {
            Side::Response if rust.null != spec.null => self.problem(
                path,
                if rust.null {
                    "the server may send null; the spec does not allow it".into()
                } else {
                    "the spec allows null; the server never sends it".into()
                },
            ),
            Side::Request if spec.null && !rust.null => {
                self.problem(path, "the spec allows null; the server refuses it".into())
            }
            _ => {}
        }
        let scalars = |n: &Node| (n.boolean, n.integer, n.number, n.string.is_some());
        if scalars(rust) != scalars(spec)
            || rust.array.is_some() != spec.array.is_some()
            || rust.object.is_some() != spec.object.is_some()
        {
            self.problem(
                path,
                format!(
                    "the server: {}; the spec: {}",
                    rust.describe(),
                    spec.describe()
                ),
            );
            return;
        }
        match (&rust.string, &spec.string) {
            (Some(Strings::Of(r)), Some(Strings::Of(s))) if r != s => self.problem(
                path,
                format!(
                    "values only the server has: {:?}; only the spec: {:?}",
                    r.difference(s).collect::<Vec<_>>(),
                    s.difference(r).collect::<Vec<_>>()
                ),
            ),
            (Some(Strings::Of(r)), Some(Strings::Any)) => self.problem(
                path,
                format!("the server's values {r:?}; the spec lists none"),
            ),
            // A Rust `String` the spec documents as an enum or a const: the spec is the
            // more precise of the two.
            _ => {}
        }
        if let (Some(r), Some(s)) = (&rust.array, &spec.array) {
            self.node(&format!("{path}[]"), r, s);
        }
        if let (Some(r), Some(s)) = (&rust.object, &spec.object) {
            self.objects(path, r, s);
        }
    }

    fn objects(&mut self, path: &str, rust: &Objects, spec: &Objects) {
        match (rust, spec) {
            (Objects::One(r), Objects::One(s)) => self.obj(path, r, s),
            (
                Objects::Tagged {
                    tag: rt,
                    variants: rv,
                },
                Objects::Tagged {
                    tag: st,
                    variants: sv,
                },
            ) => {
                if rt != st {
                    self.problem(
                        path,
                        format!("tagged by {rt} in the server, {st} in the spec"),
                    );
                    return;
                }
                let (rk, sk): (BTreeSet<_>, BTreeSet<_>) =
                    (rv.keys().collect(), sv.keys().collect());
                if rk != sk {
                    self.problem(
                        path,
                        format!(
                            "{rt} values only the server has: {:?}; only the spec: {:?}",
                            rk.difference(&sk).collect::<Vec<_>>(),
                            sk.difference(&rk).collect::<Vec<_>>()
                        ),
                    );
                }
                for (value, r) in rv {
                    if let Some(s) = sv.get(value) {
                        self.obj(&format!("{path}<{rt}={value}>"), r, s);
                    }
                }
            }
            // Untagged alternatives (serde's `untagged`, the spec's `anyOf`): paired by the
            // properties each holds, which must tell them apart.
            (Objects::Untagged(rv), Objects::Untagged(sv)) if rv.len() == sv.len() => {
                let keys = |o: &Obj| o.props.keys().cloned().collect::<BTreeSet<String>>();
                for (i, r) in rv.iter().enumerate() {
                    match sv.iter().find(|s| keys(s) == keys(r)) {
                        Some(s) => self.obj(&format!("{path}<shape {i}>"), r, s),
                        None => self.problem(
                            path,
                            format!(
                                "the server's shape with properties {:?} is not among the spec's",
                                keys(r)
                            ),
                        ),
                    }
                }
            }
            (r, s) => self.problem(
                path,
                format!(
                    "the server's objects are {}, the spec's {}",
                    shape(r),
                    shape(s)
                ),
            ),
        }
    }

    fn obj(&mut self, path: &str, rust: &Obj, spec: &Obj) {
        let at = |name: &str| {
            if path.is_empty() {
                name.to_string()
            } else {
                format!("{path}.{name}")
            }
        };
        let only_rust: Vec<_> = rust
            .props
            .keys()
            .filter(|k| !spec.props.contains_key(*k))
            .collect();
        let only_spec: Vec<_> = spec
            .props
            .keys()
            .filter(|k| !rust.props.contains_key(*k))
            .collect();
        if !only_rust.is_empty() {
            self.problem(path, format!("properties the spec lacks: {only_rust:?}"));
        }
        if !only_spec.is_empty() {
            self.problem(path, format!("properties the server lacks: {only_spec:?}"));
        }
        let (always, not_required): (&str, &str) = match self.side {
            Side::Response => (
                "the server always sends",
                "the spec requires what the server may omit",
            ),
            Side::Request => (
                "the server requires",
                "the spec requires what the server lets a client omit",
            ),
        };
        // (A property only one side has is reported above, not again here.)
        let unrequired: Vec<_> = rust
            .required
            .difference(&spec.required)
            .filter(|k| spec.props.contains_key(*k))
            .collect();
        let overrequired: Vec<_> = spec
            .required
            .difference(&rust.required)
            .filter(|k| rust.props.contains_key(*k) || !spec.props.contains_key(*k))
            .collect();
        if !unrequired.is_empty() {
            self.problem(
                path,
                format!("{always} {unrequired:?}; the spec does not require it"),
            );
        }
        if !overrequired.is_empty() {
            self.problem(path, format!("{not_required}: {overrequired:?}"));
        }
        if self.side == Side::Request && rust.closed != spec.closed {
            self.problem(
                path,
                if rust.closed {
                    "the server refuses unknown properties; the spec has no \
                     `additionalProperties: false`"
                        .into()
                } else {
                    "the spec refuses unknown properties; the server ignores them".into()
                },
            );
        }
        for (name, r) in &rust.props {
            let Some(s) = spec.props.get(name) else {
                continue;
            };
            let mut r = r.clone();
            if self.side == Side::Response && !rust.required.contains(name) {
                // Skipped when `None` (the only `skip_serializing_if` on the wire, checked
                // below): absent, never `null`.
                r.null = false;
            }
            self.node(&at(name), &r, s);
        }
    }
}

fn shape(o: &Objects) -> String {
    match o {
        Objects::One(_) => "of one shape".into(),
        Objects::Tagged { tag, .. } => format!("tagged by {tag}"),
        Objects::Untagged(v) => format!("{} shapes without a tag", v.len()),
    }
}

/// The disagreements of one entry, each prefixed with the entry.
fn disagreements(entry: &Entry, spec_doc: &Doc) -> Vec<String> {
    let what = format!(
        "{} ({}, {:?})",
        entry.schema,
        short((entry.rust)()),
        entry.side
    );
    let rust_value = (entry.generate)(entry.side);
    let empty = Map::new();
    let rust_defs = rust_value
        .get("$defs")
        .and_then(Value::as_object)
        .unwrap_or(&empty);
    let rust_doc = Doc::new(rust_defs, "#/$defs/");
    let mut rust = rust_doc.node(&rust_value);
    let nested = NESTED.iter().filter(|(s, _)| *s == entry.schema);
    for adjust in entry.adjust.iter().chain(nested.map(|(_, a)| a)) {
        apply(&mut rust, adjust, &what);
    }
    let spec = spec_doc.node(&serde_json::json!({
        "$ref": format!("#/components/schemas/{}", entry.schema)
    }));
    let mut compare = Compare {
        side: entry.side,
        root: "(body)",
        problems: Vec::new(),
    };
    compare.node("", &rust, &spec);
    compare
        .problems
        .into_iter()
        .map(|p| format!("{what} {p}"))
        .collect()
}

/// The spec's query parameters of an operation, as the schema of an object (a query string
/// takes no other parameters: the server refuses unknown ones, `deny_unknown_fields`).
fn query_parameters(spec: &Value, method: &str, path: &str) -> Option<Value> {
    let item = &spec["paths"][path];
    let parameters = item["parameters"]
        .as_array()
        .into_iter()
        .chain(item[method]["parameters"].as_array())
        .flatten()
        .map(|p| match p["$ref"].as_str() {
            Some(r) => &spec["components"]["parameters"][r.rsplit('/').next().unwrap()],
            None => p,
        })
        .filter(|p| p["in"] == "query");
    let mut properties = Map::new();
    let mut required = Vec::new();
    for p in parameters {
        let name = p["name"].as_str().expect("a parameter's name").to_string();
        if p["required"] == Value::Bool(true) {
            required.push(Value::String(name.clone()));
        }
        properties.insert(name, p["schema"].clone());
    }
    (!properties.is_empty()).then(|| {
        serde_json::json!({
            "type": "object",
            "properties": properties,
            "required": required,
            "additionalProperties": false,
        })
    })
}

// ---------------------------------------------------------------- the tests

fn spec_schemas(spec: &Value) -> &Map<String, Value> {
    spec["components"]["schemas"]
        .as_object()
        .expect("components/schemas")
}

#[test]
fn every_body_is_the_spec_schema_of_the_same_name() {
    let spec = spec();
    let doc = Doc::new(spec_schemas(&spec), "#/components/schemas/");
    let problems: Vec<String> = ENTRIES
        .iter()
        .flat_map(|e| disagreements(e, &doc))
        .collect();
    assert!(
        problems.is_empty(),
        "crates/precond/src/api.rs and api/openapi.yaml disagree ({}):\n{}",
        problems.len(),
        problems.join("\n")
    );
}

#[test]
fn every_spec_schema_is_checked_or_listed_with_a_reason() {
    let spec = spec();
    let schemas = spec_schemas(&spec);
    let doc = Doc::new(schemas, "#/components/schemas/");
    let mut listed = BTreeMap::new();
    let names = ENTRIES
        .iter()
        .map(|e| (e.schema, "ENTRIES"))
        .chain(REACHED.iter().map(|s| (*s, "REACHED")))
        .chain(NOT_TYPED.iter().map(|(s, _)| (*s, "NOT_TYPED")));
    for (name, list) in names {
        assert!(
            schemas.contains_key(name),
            "{list} names {name}: no such schema in the spec"
        );
        let previous = listed.insert(name, list);
        assert!(
            previous.is_none() || previous == Some(list) && list == "ENTRIES",
            "{name} is in {list} and {previous:?}"
        );
    }
    let unlisted: Vec<_> = schemas
        .keys()
        .filter(|k| !listed.contains_key(k.as_str()))
        .collect();
    assert!(
        unlisted.is_empty(),
        "spec schemas neither compared with a Rust type (ENTRIES), reached from one (REACHED) \
         nor listed with a reason (NOT_TYPED): {unlisted:?}"
    );
    // What REACHED claims: each is compared as part of an entry.
    for e in ENTRIES {
        disagreements(e, &doc);
    }
    let followed = doc.followed.borrow();
    for name in REACHED {
        assert!(
            followed.contains(*name),
            "REACHED {name} is reached from no entry"
        );
    }
}

/// The comparison reads a response property that is not required as one skipped when `None`
/// (so never `null`): true while `Option::is_none` is the only `skip_serializing_if` of the
/// wire types.
#[test]
fn the_wire_types_skip_only_absent_options() {
    for file in [
        "crates/precond/src/api.rs",
        "crates/precond/src/settings/mod.rs",
        "crates/precond/src/settings/custom.rs",
        "crates/precond-core/src/gp/mod.rs",
        "crates/precond-core/src/mde/mod.rs",
        "crates/precond-core/src/mde/estimator.rs",
        "crates/precond-core/src/mde/selection.rs",
        "crates/precond-core/src/domain/mod.rs",
    ] {
        let text = std::fs::read_to_string(format!("{}/../../{file}", env!("CARGO_MANIFEST_DIR")))
            .expect("source file");
        for (i, line) in text.lines().enumerate() {
            if let Some(rest) = line.split("skip_serializing_if").nth(1) {
                assert!(
                    rest.trim_start().starts_with("= \"Option::is_none\""),
                    "{file}:{}: only `Option::is_none` is understood by contract::bodies",
                    i + 1
                );
            }
        }
    }
}

#[test]
fn every_query_string_is_the_specs_query_parameters() {
    let spec = spec();
    let doc = Doc::new(spec_schemas(&spec), "#/components/schemas/");
    let mut problems = Vec::new();
    for q in QUERIES {
        let what = format!(
            "{} {} query ({})",
            q.method.to_uppercase(),
            q.path,
            short((q.rust)())
        );
        let Some(parameters) = query_parameters(&spec, q.method, q.path) else {
            problems.push(format!("{what}: the spec has no query parameters there"));
            continue;
        };
        let rust_value = (q.generate)(Side::Request);
        let empty = Map::new();
        let rust_defs = rust_value
            .get("$defs")
            .and_then(Value::as_object)
            .unwrap_or(&empty);
        let rust = Doc::new(rust_defs, "#/$defs/").node(&rust_value);
        let mut compare = Compare {
            side: Side::Request,
            root: "(query)",
            problems: Vec::new(),
        };
        compare.node("", &rust, &doc.node(&parameters));
        problems.extend(compare.problems.into_iter().map(|p| format!("{what} {p}")));
    }
    // Every operation with query parameters is listed.
    for (path, item) in spec["paths"].as_object().expect("paths") {
        for method in item.as_object().unwrap().keys() {
            let listed = QUERIES
                .iter()
                .any(|q| q.method == method.as_str() && q.path == path.as_str());
            if !listed && query_parameters(&spec, method, path).is_some() {
                problems.push(format!(
                    "{} {path} takes query parameters: add its query type to QUERIES",
                    method.to_uppercase()
                ));
            }
        }
    }
    assert!(
        problems.is_empty(),
        "crates/precond/src/api.rs and api/openapi.yaml disagree on query strings ({}):\n{}",
        problems.len(),
        problems.join("\n")
    );
}
