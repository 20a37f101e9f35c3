//! The `model` subcommands: argument structs shared by the command line (clap) and the JSON-lines
//! batch mode (serde), and their evaluation to JSON.
//!
//! Field names are the flag names with underscores. Every range check is the model's own, so a
//! bad value gets the same message (field, value, allowed range) from a flag and from a batch line.

mod args;
mod error;
mod optics;
mod scene;
mod sensor;
mod text;

pub use error::{CommandError, LayerError};
pub use optics::*;
pub use scene::*;
pub use sensor::*;
pub use text::{compact, echo, tidy, ECHO_MAX};

#[cfg(test)]
mod tests {
    use super::*;

    /// A metal gets the pseudo-Brewster angle (copper 68.454 deg, the published value in
    /// crates/model/tests/reference.rs, to its 6e-4 deg) with Rp there (0.428, between 0 and
    /// Rp at 60 deg); a dielectric keeps atan(n) = 56.659 deg and no pseudo angle.
    #[test]
    fn fresnel_reports_pseudo_brewster_for_metals_only() {
        let copper = fresnel(&FresnelArgs {
            n: Some(1.02),
            k: 2.577,
            theta_i_deg: Some(60.0),
        })
        .unwrap();
        assert!(copper.get("brewster_deg").is_none(), "{copper}");
        let pb = copper["pseudo_brewster_deg"].as_f64().unwrap();
        assert!((pb - 68.454).abs() < 6e-4, "{pb}");
        let rp_min = copper["rp_min"].as_f64().unwrap();
        assert!(
            rp_min > 0.0 && rp_min < copper["Rp"].as_f64().unwrap(),
            "{copper}"
        );
        let glass = fresnel(&FresnelArgs {
            n: Some(1.52),
            k: 0.0,
            theta_i_deg: Some(60.0),
        })
        .unwrap();
        assert!(glass.get("pseudo_brewster_deg").is_none(), "{glass}");
        assert!((glass["brewster_deg"].as_f64().unwrap() - 56.659293).abs() < 1e-6);
    }

    /// The rooftop lit by its 10-degree sky table, asked for 1e-9: every material states its
    /// floor (above 1e-4 of S0: a 10-degree grid), a note that 1e-9 is below it, an
    /// integration tolerance of at least a quarter of it, and an error estimate that includes
    /// it. The same scene with the model sky has no floor at all.
    #[test]
    fn scene_json_states_the_table_floor() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../examples");
        let table = load_scene(&root.join("rooftop_table.toml")).unwrap();
        let v = scene_json(&table, 1e-9).unwrap();
        for m in v["materials"].as_array().unwrap() {
            let f = &m["error_floor"];
            let relative = f["relative"].as_f64().unwrap();
            assert!(relative > 1e-4, "{m}");
            assert!(f["note"].as_str().unwrap().contains("below"), "{f}");
            assert!(f["source"].as_str().unwrap().contains("sky table"), "{f}");
            let to = f["integrated_to"].as_f64().unwrap();
            assert!(
                to >= 0.9 * polar_model::scene::FLOOR_FRACTION * relative,
                "{f}"
            );
            assert!(m["error_estimate"].as_f64().unwrap() >= relative, "{m}");
        }
        let model = load_scene(&root.join("rooftop.toml")).unwrap();
        let v = scene_json(&model, 1e-3).unwrap();
        for m in v["materials"].as_array().unwrap() {
            assert!(m.get("error_floor").is_none(), "{m}");
        }
    }

    #[test]
    fn numbers_print_compactly_and_long_text_is_cut() {
        assert_eq!(compact(1e300), "1e300");
        assert_eq!(compact(-1e-300), "-1e-300");
        assert_eq!(compact(95.0), "95");
        assert_eq!(compact(0.001), "0.001");
        assert_eq!(compact(f64::NAN), "NaN");
        let long = "y".repeat(1000);
        let e = echo(&long);
        assert!(
            e.contains('…') && e.ends_with("(1000 characters)") && e.len() < 120,
            "{e}"
        );
        assert_eq!(echo("3x3"), "\"3x3\"");
        // Foreign messages: long quoted spans cut, long numbers compact, once.
        let msg = format!(
            "invalid type: string \"{long}\", unknown field `{long}`, value {}.0",
            "1".to_string() + &"0".repeat(300)
        );
        let t = tidy(&msg);
        assert!(t.len() < 300, "{t}");
        assert!(
            t.contains("value 1e300") && t.matches("(1000 characters)").count() == 2,
            "{t}"
        );
        assert_eq!(tidy(&t), t);
        assert_eq!(
            tidy(&format!("x = {}", echo(&long))),
            format!("x = {}", echo(&long))
        );
        assert_eq!(
            tidy("a 12345 b_123456789012345678901234 \"q\""),
            "a 12345 b_123456789012345678901234 \"q\""
        );
    }
}
