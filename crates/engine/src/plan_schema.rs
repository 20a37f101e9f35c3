//! The plan file's keys from the code's own definitions: a JSON Schema of the plan as written
//! (serde's layout of [`crate::plan::Plan`]: `kind`, each kind's section and the shared
//! sections, with every field's doc comment as its description and every serde default as
//! its default), and the Markdown reference `docs/PLAN-KEYS.md` generated from that schema, so
//! the reference cannot drift from the parser (a test compares the two).

use serde_json::{Map, Value};

/// The JSON Schema (draft 2020-12) of a plan file.
pub fn plan_schema() -> Value {
    let schema = schemars::schema_for!(crate::plan::Plan);
    schema.to_value()
}

/// The Markdown reference of every plan key: one table per section (`[capture]`,
/// `[continuous.from_planner]`, ...) with each key's type, default and description.
pub fn plan_keys_markdown() -> String {
    let schema = plan_schema();
    let defs = schema
        .get("$defs")
        .and_then(Value::as_object)
        .cloned()
        .unwrap_or_default();
    let mut out = String::from(HEADER);
    let mut sections = Vec::new();
    table(&schema, "", &defs, &mut sections);
    for (name, rows) in sections {
        out.push_str(&format!("\n## {name}\n\n"));
        out.push_str("| key | type | default | description |\n|---|---|---|---|\n");
        for r in rows {
            out.push_str(&format!(
                "| `{}` | {} | {} | {} |\n",
                r[0], r[1], r[2], r[3]
            ));
        }
    }
    out
}

const HEADER: &str = "# Plan file keys\n\n\
Every key of a plan file (TOML or YAML), generated from the parser's own definitions by \
`polarimeter plan schema --markdown`; `polarimeter plan schema` prints the same as a JSON \
Schema. A test fails when this file and the code disagree. A key without a default must be \
given; a section marked optional may be left out. `kind` chooses which one of the kinds' \
sections the plan has; the example plans in examples/plans/ show each kind.\n";

/// `schema` with a `$ref` followed into `defs`, and whether it allows null (an `Option`).
fn resolve<'a>(schema: &'a Value, defs: &'a Map<String, Value>) -> (&'a Value, bool) {
    if let Some(r) = schema.get("$ref").and_then(Value::as_str) {
        let name = r.rsplit('/').next().unwrap_or(r);
        if let Some(d) = defs.get(name) {
            return (d, false);
        }
    }
    for key in ["anyOf", "oneOf"] {
        if let Some(alts) = schema.get(key).and_then(Value::as_array) {
            let non_null: Vec<&Value> = alts
                .iter()
                .filter(|a| a.get("type").and_then(Value::as_str) != Some("null"))
                .collect();
            if non_null.len() == 1 && non_null.len() < alts.len() {
                let (inner, _) = resolve(non_null[0], defs);
                return (inner, true);
            }
        }
    }
    (schema, false)
}

/// Whether `schema` is a table of named keys (a section).
fn is_section(schema: &Value) -> bool {
    schema.get("properties").is_some_and(Value::is_object)
}

/// The section `path`'s rows, then its subsections', into `sections`.
fn table(
    schema: &Value,
    path: &str,
    defs: &Map<String, Value>,
    sections: &mut Vec<(String, Vec<[String; 4]>)>,
) {
    let Some(props) = schema.get("properties").and_then(Value::as_object) else {
        return;
    };
    let required: Vec<&str> = schema
        .get("required")
        .and_then(Value::as_array)
        .map(|r| r.iter().filter_map(Value::as_str).collect())
        .unwrap_or_default();
    let title = if path.is_empty() {
        "Top level".to_string()
    } else {
        format!("`[{path}]`")
    };
    let at = sections.len();
    sections.push((title, Vec::new()));
    let mut nested = Vec::new();
    for (key, field) in props {
        let (inner, _) = resolve(field, defs);
        let description = describe(field, inner);
        let child = if path.is_empty() {
            key.clone()
        } else {
            format!("{path}.{key}")
        };
        if is_section(inner) {
            let given = if required.contains(&key.as_str()) {
                "required"
            } else {
                "optional"
            };
            sections[at].1.push([
                key.clone(),
                format!("section ({given})"),
                "".into(),
                description,
            ]);
            nested.push((inner, child));
            continue;
        }
        let default = match field.get("default") {
            Some(Value::Null) => "none".to_string(),
            Some(v) => format!("`{v}`"),
            None if required.contains(&key.as_str()) => "(required)".to_string(),
            None => "none".to_string(),
        };
        sections[at]
            .1
            .push([key.clone(), type_of(inner, defs), default, description]);
    }
    for (inner, child) in nested {
        table(inner, &child, defs, sections);
    }
}

/// A field's description: its own doc comment, else its type's; one line, pipes escaped.
fn describe(field: &Value, inner: &Value) -> String {
    let text = field
        .get("description")
        .or_else(|| inner.get("description"))
        .and_then(Value::as_str)
        .unwrap_or("");
    // Rustdoc's links (`[`Plan::from_path`]`) read as plain code here.
    text.split_whitespace()
        .collect::<Vec<_>>()
        .join(" ")
        .replace("[`", "`")
        .replace("`]", "`")
        .replace('|', "\\|")
}

/// A type in words: `integer >= 0`, `number`, `string`, `one of "a", "b"`, `list of number`.
fn type_of(schema: &Value, defs: &Map<String, Value>) -> String {
    let (schema, _) = resolve(schema, defs);
    if let Some(values) = enum_values(schema) {
        return format!("one of {}", values.join(", "));
    }
    let kind = match schema.get("type") {
        Some(Value::String(t)) => t.clone(),
        Some(Value::Array(ts)) => ts
            .iter()
            .filter_map(Value::as_str)
            .filter(|t| *t != "null")
            .collect::<Vec<_>>()
            .join(" or "),
        _ => "value".to_string(),
    };
    match kind.as_str() {
        "array" => {
            let item = schema
                .get("items")
                .map_or("value".to_string(), |i| type_of(i, defs));
            format!("list of {item}")
        }
        "integer" => match schema.get("minimum").and_then(Value::as_f64) {
            Some(m) => format!("integer >= {m}"),
            None => "integer".into(),
        },
        "object" => "table".into(),
        other => other.to_string(),
    }
}

/// The allowed values of an enum schema (`enum`, or `oneOf` of `const`s), quoted.
fn enum_values(schema: &Value) -> Option<Vec<String>> {
    if let Some(values) = schema.get("enum").and_then(Value::as_array) {
        return Some(values.iter().map(Value::to_string).collect());
    }
    let alts = schema.get("oneOf").and_then(Value::as_array)?;
    alts.iter()
        .map(|a| a.get("const").map(Value::to_string))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `docs/PLAN-KEYS.md` is what the code generates: a key added, renamed, documented
    /// differently or given another default in the plan's types changes the generated text,
    /// and this test names the first line that differs (regenerate with `polarimeter plan
    /// schema --markdown > docs/PLAN-KEYS.md`).
    #[test]
    fn plan_keys_reference_is_current() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../docs/PLAN-KEYS.md");
        let written = std::fs::read_to_string(path).unwrap_or_default();
        let generated = plan_keys_markdown();
        if written != generated {
            let line = written
                .lines()
                .zip(generated.lines())
                .position(|(a, b)| a != b)
                .unwrap_or(written.lines().count().min(generated.lines().count()));
            panic!(
                "docs/PLAN-KEYS.md differs from the code at line {}: written {:?}, generated \
                 {:?}; regenerate with `polarimeter plan schema --markdown > docs/PLAN-KEYS.md`",
                line + 1,
                written.lines().nth(line),
                generated.lines().nth(line)
            );
        }
    }

    /// The schema knows every kind and every section the parser reads: `kind`'s allowed
    /// values are the six kinds, and each kind's section, `[policy]`, `[suspender]`, `[site]`,
    /// `[simulation]` and `[storage]` are properties of the top level; the capture's
    /// `angles_deg` is a list of numbers, and `continuous.trigger` one of `"encoder"`,
    /// `"timestamps"` with the default `"encoder"`.
    #[test]
    fn schema_has_every_kind_and_section() {
        let s = plan_schema();
        let props = s["properties"].as_object().expect("properties");
        for key in [
            "name",
            "kind",
            "capture",
            "calibrate-noise",
            "calibrate-analyzer",
            "time-lapse",
            "adaptive",
            "continuous",
            "policy",
            "suspender",
            "site",
            "simulation",
            "storage",
        ] {
            assert!(props.contains_key(key), "{key} missing: {props:?}");
        }
        let md = plan_keys_markdown();
        assert!(
            md.contains("| `kind` | one of \"capture\", \"calibrate-noise\", \"calibrate-analyzer\", \"time-lapse\", \"adaptive\", \"continuous\""),
            "{md}"
        );
        assert!(md.contains("| `angles_deg` | list of number"), "{md}");
        assert!(
            md.contains("| `trigger` | one of \"encoder\", \"timestamps\" | `\"encoder\"`"),
            "{md}"
        );
    }
}
