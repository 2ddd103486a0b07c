//! `api/openapi.yaml`'s schemas are what `precond openapi` generates from the wire types and
//! `api/schemas.yaml`: regenerating gives no difference.

use precond_tools::openapi::{Annotations, document};

fn read(file: &str) -> String {
    std::fs::read_to_string(format!("{}/../../api/{file}", env!("CARGO_MANIFEST_DIR")))
        .unwrap_or_else(|e| panic!("api/{file}: {e}"))
}

#[test]
fn the_schemas_are_generated_from_the_wire_types() {
    let current = read("openapi.yaml");
    let notes = Annotations::parse(&read("schemas.yaml")).expect("api/schemas.yaml is read");
    let generated = document(&current, &notes)
        .unwrap_or_else(|problems| panic!("cannot generate:\n  {}", problems.join("\n  ")));
    if generated != current {
        let line = generated
            .lines()
            .zip(current.lines())
            .position(|(a, b)| a != b)
            .map_or_else(
                || "at the end".to_string(),
                |n| format!("at line {}", n + 1),
            );
        panic!(
            "api/openapi.yaml is not what the wire types and api/schemas.yaml generate (first \
             difference {line}): run `cargo run -- openapi` and commit the result"
        );
    }
}
