//! The router and `api/openapi.yaml` describe the same routes.

use precond::http::routes;
use std::collections::BTreeSet;

fn spec() -> serde_yaml::Value {
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/api/openapi.yaml"))
        .expect("api/openapi.yaml exists");
    serde_yaml::from_str(&text).expect("api/openapi.yaml is YAML")
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
    let missing_in_spec: Vec<_> = served.difference(&in_spec).collect();
    let not_served: Vec<_> = in_spec.difference(&served).collect();
    assert!(
        missing_in_spec.is_empty(),
        "served but not in the spec: {missing_in_spec:?}"
    );
    assert!(
        not_served.is_empty(),
        "in the spec but not served: {not_served:?}"
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
