//! The plan file's keys from the code's own definitions: a JSON Schema of the plan as written
//! (serde's layout of [`crate::plan::Plan`]: `kind`, each kind's section and the shared
//! sections, with every field's doc comment as its description and every serde default as
//! its default), and a Markdown reference of any such schema ([`keys_markdown`]: one table
//! per section), from which `docs/FILE-KEYS.md` is generated, so the reference cannot drift
//! from the parsers (the CLI's test compares the two).

use serde_json::{Map, Value};

/// The JSON Schema (draft 2020-12) of a plan file.
pub fn plan_schema() -> Value {
    let schema = schemars::schema_for!(crate::plan::Plan);
    schema.to_value()
}

/// The Markdown reference of every key `schema` describes: one table per section, headed
/// `{level} [section]` (`level` is the heading's `#`s), with each key's type, default and
/// description.
pub fn keys_markdown(schema: &Value, level: &str) -> String {
    let defs = schema
        .get("$defs")
        .and_then(Value::as_object)
        .cloned()
        .unwrap_or_default();
    let mut out = String::new();
    let mut sections = Vec::new();
    table(schema, "", false, &defs, &mut sections);
    for (name, rows) in sections {
        out.push_str(&format!("\n{level} {name}\n\n"));
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

/// The items of a list of tables (`[[material]]`), if `schema` is one.
fn table_items<'a>(schema: &'a Value, defs: &'a Map<String, Value>) -> Option<&'a Value> {
    let (items, _) = resolve(schema.get("items")?, defs);
    is_section(items).then_some(items)
}

/// The section `path`'s rows (`[[path]]` for a list of tables), then its subsections', into
/// `sections`.
fn table(
    schema: &Value,
    path: &str,
    list: bool,
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
    let title = match (path.is_empty(), list) {
        (true, _) => "Top level".to_string(),
        (false, true) => format!("`[[{path}]]` (a list of tables)"),
        (false, false) => format!("`[{path}]`"),
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
            nested.push((inner, child, false));
            continue;
        }
        if let Some(items) = table_items(inner, defs) {
            sections[at].1.push([
                key.clone(),
                format!("list of tables (`[[{child}]]`)"),
                "none".into(),
                description,
            ]);
            nested.push((items, child, true));
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
    for (inner, child, list) in nested {
        table(inner, &child, list, defs, sections);
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
            // A tuple (`[x, y]`) has its items' schemas in `prefixItems`.
            let first = schema.get("items").or_else(|| {
                schema
                    .get("prefixItems")
                    .and_then(Value::as_array)
                    .and_then(|p| p.first())
            });
            let item = first.map_or("value".to_string(), |i| type_of(i, defs));
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
        let md = keys_markdown(&s, "##");
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
