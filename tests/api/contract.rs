//! The router and `api/openapi.yaml` describe the same routes and the same error codes, and
//! (`bodies`) the same request and response bodies, the schemas generated from them (`generated`).

mod bodies;
mod generated;

use precond::domain::DynamicsError;
use precond::http::error::ApiError;
use precond::http::routes;
use precond::service::Error;
use std::collections::BTreeSet;

fn spec() -> serde_yaml::Value {
    let text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../api/openapi.yaml"
    ))
    .expect("api/openapi.yaml exists");
    serde_yaml::from_str(&text).expect("api/openapi.yaml is YAML")
}

/// Asserts that the server's `ours` and the spec's `theirs` hold the same items; the failure
/// lists what only one side has, under `only_ours` or `only_theirs`.
fn assert_same<T: Ord + std::fmt::Debug>(
    ours: &BTreeSet<T>,
    theirs: &BTreeSet<T>,
    only_ours: &str,
    only_theirs: &str,
) {
    let extra: Vec<_> = ours.difference(theirs).collect();
    let missing: Vec<_> = theirs.difference(ours).collect();
    assert!(extra.is_empty(), "{only_ours}: {extra:?}");
    assert!(missing.is_empty(), "{only_theirs}: {missing:?}");
}

#[test]
fn every_route_is_in_the_spec_and_every_spec_route_is_served() {
    let spec = spec();
    assert!(spec["openapi"].as_str().unwrap().starts_with("3.1"));
    let mut in_spec = BTreeSet::new();
    for (path, item) in spec["paths"].as_mapping().expect("paths") {
        for (method, _) in item.as_mapping().unwrap() {
            let method = method.as_str().unwrap().to_uppercase();
            if ["GET", "POST", "PUT", "PATCH", "DELETE"].contains(&method.as_str()) {
                in_spec.insert((method, path.as_str().unwrap().to_string()));
            }
        }
    }
    let served: BTreeSet<(String, String)> = routes()
        .iter()
        .map(|r| (r.method.to_string(), r.path.to_string()))
        .collect();
    assert_same(
        &served,
        &in_spec,
        "served but not in the spec",
        "in the spec but not served",
    );
}

#[test]
fn the_spec_describes_the_error_shape() {
    let spec = spec();
    let schemas = &spec["components"]["schemas"];
    let mut inner = &schemas["Error"]["properties"]["error"];
    if let Some(r) = inner["$ref"].as_str() {
        inner = &schemas[r.rsplit('/').next().unwrap()];
    }
    let inner = &inner["properties"];
    for field in ["code", "message", "details"] {
        assert!(!inner[field].is_null(), "Error.error.{field} is described");
    }
}

/// One error of every kind the server can answer. The match below has no wildcard, so a new
/// variant of `ApiError`, `service::Error` or `DynamicsError` does not compile until it is
/// listed here, and the test below then checks its code against the spec.
fn one_of_every_error() -> Vec<ApiError> {
    let errors = vec![
        ApiError::BadRequest("malformed".into()),
        ApiError::PayloadTooLarge { limit: 1 },
        ApiError::UnsupportedMediaType("form".into()),
        ApiError::RequestTimeout("slow".into()),
        ApiError::MethodNotAllowed,
        ApiError::Unavailable("database".into()),
        ApiError::Unauthorized,
        ApiError::Forbidden("role".into()),
        ApiError::Service(Error::validation("field", "reason")),
        ApiError::Service(Error::NotFound("nothing".into())),
        ApiError::Service(Error::Conflict("twice".into())),
        ApiError::Service(Error::LeaseHeld {
            proposal_id: 1,
            client_id: "r1".into(),
            start: vec![0.0],
            goal: vec![1.0],
        }),
        ApiError::Service(Error::NoPlan {
            extensions: 1,
            candidates: Vec::new(),
        }),
        ApiError::Service(Error::Overloaded {
            retry_after_secs: 1,
        }),
        ApiError::Service(Error::DeadlineExceeded {
            extensions: 1,
            timeout_ms: 1,
            retry_after_secs: 1,
        }),
        ApiError::Service(Error::Cancelled),
        ApiError::Service(Error::LimitReached("full".into())),
        ApiError::Service(Error::Dynamics(DynamicsError::Timeout {
            model: "m".into(),
            timeout_ms: 1,
        })),
        ApiError::Service(Error::Dynamics(DynamicsError::Unavailable {
            model: "m".into(),
            reason: "down".into(),
        })),
        ApiError::Service(Error::Dynamics(DynamicsError::Busy {
            model: "m".into(),
            reason: "full".into(),
        })),
        ApiError::Service(Error::Dynamics(DynamicsError::NotAllowed {
            model: "m".into(),
            reason: "revoked".into(),
        })),
        ApiError::Service(Error::Dynamics(DynamicsError::ClientSide)),
        ApiError::Service(Error::KeyReused {
            field: "transitions[0].a[0]".into(),
            difference: "transitions[0].a[0] was 1 and is now 2".into(),
        }),
        ApiError::Service(Error::ExportsBusy {
            limit: 4,
            retry_after_secs: 5,
        }),
        ApiError::Service(Error::StorageFull("database or disk is full".into())),
        ApiError::Service(Error::DatabaseUnavailable("pool timed out".into())),
        ApiError::Service(Error::PrefixStored {
            trajectory_id: 7,
            error: Box::new(Error::NoPlan {
                extensions: 1,
                candidates: Vec::new(),
            }),
        }),
        ApiError::Service(Error::ImportStopped {
            stop: Box::new(precond::import::ImportStop {
                episode: Some(3),
                first_step: Some(0),
                stored_before: precond::import::ImportReport::default(),
            }),
            error: Box::new(Error::KeyReused {
                field: "transitions[0].a[0]".into(),
                difference: "transitions[0].a[0] was 1 and is now 2".into(),
            }),
        }),
        // An error with no details of its own: the import's alone.
        ApiError::Service(Error::ImportStopped {
            stop: Box::new(precond::import::ImportStop {
                episode: None,
                first_step: None,
                stored_before: precond::import::ImportReport::default(),
            }),
            error: Box::new(Error::LimitReached("transitions".into())),
        }),
        ApiError::Service(Error::Internal(anyhow::anyhow!("bug"))),
    ];
    for e in &errors {
        match e {
            ApiError::BadRequest(_)
            | ApiError::PayloadTooLarge { .. }
            | ApiError::UnsupportedMediaType(_)
            | ApiError::RequestTimeout(_)
            | ApiError::MethodNotAllowed
            | ApiError::Unavailable(_)
            | ApiError::Unauthorized
            | ApiError::Forbidden(_) => {}
            ApiError::Service(s) => match s {
                Error::Validation { .. }
                | Error::NotFound(_)
                | Error::Conflict(_)
                | Error::LeaseHeld { .. }
                | Error::NoPlan { .. }
                | Error::Overloaded { .. }
                | Error::DeadlineExceeded { .. }
                | Error::Cancelled
                | Error::LimitReached(_)
                | Error::KeyReused { .. }
                | Error::ExportsBusy { .. }
                | Error::StorageFull(_)
                | Error::DatabaseUnavailable(_)
                | Error::PrefixStored { .. }
                | Error::ImportStopped { .. }
                | Error::Internal(_) => {}
                Error::Dynamics(d) => match d {
                    DynamicsError::Timeout { .. }
                    | DynamicsError::Unavailable { .. }
                    | DynamicsError::Busy { .. }
                    | DynamicsError::NotAllowed { .. }
                    | DynamicsError::ClientSide => {}
                },
            },
        }
    }
    errors
}

#[test]
fn the_error_codes_the_server_answers_are_the_specs_enum() {
    let spec = spec();
    let enumerated: BTreeSet<String> =
        spec["components"]["schemas"]["ErrorBody"]["properties"]["code"]["enum"]
            .as_sequence()
            .expect("ErrorBody.code has an enum: the one list of codes (clients check against it)")
            .iter()
            .map(|c| c.as_str().unwrap().to_string())
            .collect();
    let answered: BTreeSet<String> = one_of_every_error()
        .iter()
        .map(|e| {
            let body = serde_json::to_value(e.body()).unwrap();
            assert_eq!(body["error"]["code"], e.code(), "the body carries the code");
            e.code().to_string()
        })
        .collect();
    assert_same(
        &answered,
        &enumerated,
        "answered but not in ErrorBody.code",
        "in ErrorBody.code but never answered",
    );
}
