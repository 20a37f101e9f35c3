//! The API's OpenAPI 3.1 description, built from [`crate::routes::ROUTES`] so it cannot
//! drift from the router: each path and method, its summary, the scope it needs (as the
//! `bearer` security requirement's scope list) and the error shape.

use crate::routes::ROUTES;
use serde_json::{json, Map, Value};

/// The description, as served at `/api/v1/openapi.json`.
pub fn document() -> Value {
    let mut paths = Map::new();
    for r in ROUTES {
        let entry = paths.entry(r.path.to_string()).or_insert_with(|| json!({}));
        let mut op = json!({
            "summary": r.summary,
            "operationId": operation_id(r.method, r.path),
            "responses": responses(r.path),
        });
        match r.scope {
            Some(s) => {
                op["security"] = json!([{"bearer": [s.name()]}]);
                op["description"] = json!(format!(
                    "Needs a key with the `{}` scope (or `admin`).",
                    s.name()
                ));
            }
            None => op["security"] = json!([]),
        }
        if r.path.contains("{name}") {
            op["parameters"] = json!([{"name": "name", "in": "path", "required": true,
                "schema": {"enum": ["s0", "dolp", "aop"]}}]);
        }
        if r.path.contains("{id}") {
            op["parameters"] = json!([{"name": "id", "in": "path", "required": true,
                "schema": {"type": "integer", "minimum": 1}}]);
        }
        if r.method == "POST" && (r.path == "/api/v1/queue" || r.path.ends_with("/validate")) {
            op["requestBody"] = json!({"required": true, "content": {"application/json": {"schema": {"$ref": "#/components/schemas/Submit"}}}});
        }
        if r.path.ends_with("/move") {
            op["requestBody"] = json!({"required": true, "content": {"application/json": {"schema": {
                "type": "object", "required": ["position"], "additionalProperties": false,
                "properties": {"position": {"type": "integer", "minimum": 0}}}}}});
        }
        entry[r.method.to_lowercase()] = op;
    }
    json!({
        "openapi": "3.1.0",
        "info": {"title": "polarimeter station", "version": env!("CARGO_PKG_VERSION"),
                 "description": "An unattended rotating-analyzer polarimeter: a plan queue, run control, history, health and events."},
        "paths": paths,
        "components": {
            "securitySchemes": {"bearer": {"type": "http", "scheme": "bearer",
                "description": "An API key (pst_<id>_<64 hex digits>) from `polarimeter station key create`."}},
            "schemas": {
                "Error": {"type": "object", "required": ["error"], "properties": {
                    "error": {"type": "string"}, "field": {"type": ["string", "null"]}}},
                "NewItem": {"type": "object", "required": ["plan"], "additionalProperties": false, "properties": {
                    "plan": {"type": "string", "description": "A plan file's text."},
                    "format": {"enum": ["toml", "yaml"]},
                    "priority": {"type": "integer", "minimum": -1000, "maximum": 1000}}},
                "Submit": {"oneOf": [
                    {"$ref": "#/components/schemas/NewItem"},
                    {"type": "object", "required": ["items"], "additionalProperties": false, "properties": {
                        "items": {"type": "array", "minItems": 1, "maxItems": 100,
                                  "items": {"$ref": "#/components/schemas/NewItem"}}}}]}
            }
        }
    })
}

fn operation_id(method: &str, path: &str) -> String {
    let words: Vec<&str> = path
        .trim_start_matches("/api/v1")
        .split(['/', '.', '{', '}'])
        .filter(|w| !w.is_empty())
        .collect();
    format!("{}_{}", method.to_lowercase(), words.join("_"))
}

fn responses(path: &str) -> Value {
    let error = json!({"content": {"application/json": {"schema": {"$ref": "#/components/schemas/Error"}}}});
    let ok = if path == "/" {
        json!({"description": "The status page.", "content": {"text/html": {"schema": {"type": "string"}}}})
    } else if path.contains("/products/") {
        json!({"description": "A PNG image.", "content": {"image/png": {"schema": {"type": "string", "format": "binary"}}}})
    } else if path.ends_with("/events") {
        json!({"description": "A stream of server-sent events.", "content": {"text/event-stream": {"schema": {"type": "string"}}}})
    } else {
        json!({"description": "OK", "content": {"application/json": {"schema": {"type": "object"}}}})
    };
    let mut r = json!({"200": ok});
    for (code, what) in [
        ("400", "A field is wrong"),
        ("401", "No valid key"),
        ("403", "The key lacks the scope"),
        ("409", "Not now"),
        ("413", "The body is too large"),
    ] {
        let mut e = error.clone();
        e["description"] = json!(what);
        r[code] = e;
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_route_is_described_once_with_a_unique_operation() {
        let d = document();
        let mut ids = std::collections::BTreeSet::new();
        for r in ROUTES {
            let op = &d["paths"][r.path][r.method.to_lowercase()];
            assert!(op.is_object(), "{} {}", r.method, r.path);
            assert!(ids.insert(op["operationId"].as_str().unwrap().to_string()));
        }
    }
}
