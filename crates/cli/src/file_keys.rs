//! The reference of every file a user writes, generated from the parsers' own types: the plan
//! ([`polar_engine::plan::Plan`]), the rig file ([`polar_rig::file::RigFile`]), the scene
//! (`polar_model::scene_file`) and the camera file ([`polar_model::sensor::Camera`]), each a
//! JSON Schema (`polarimeter plan schema --file F`) and together the Markdown reference
//! `docs/FILE-KEYS.md` (`polarimeter plan schema --markdown`), which a test keeps equal to
//! the code.

use serde_json::Value;

/// The files a user writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum UserFile {
    /// A plan (TOML or YAML): what a run acquires.
    Plan,
    /// A rig file: the devices of a run.
    Rig,
    /// A scene (TOML): sun, atmosphere, band, sensor and materials.
    Scene,
    /// A camera file (TOML): the sensor's noise model and optics.
    Camera,
}

impl UserFile {
    /// All four, in the reference's order.
    pub const ALL: [UserFile; 4] = [
        UserFile::Plan,
        UserFile::Rig,
        UserFile::Scene,
        UserFile::Camera,
    ];

    /// The file's JSON Schema (draft 2020-12).
    pub fn schema(self) -> Value {
        match self {
            UserFile::Plan => polar_engine::plan_schema::plan_schema(),
            UserFile::Rig => schemars::schema_for!(polar_rig::file::RigFile).to_value(),
            UserFile::Scene => polar_model::scene_file::scene_file_schema().to_value(),
            UserFile::Camera => schemars::schema_for!(polar_model::sensor::Camera).to_value(),
        }
    }

    fn title(self) -> &'static str {
        match self {
            UserFile::Plan => "Plan file (examples/plans/)",
            UserFile::Rig => "Rig file (examples/rigs/)",
            UserFile::Scene => "Scene file (examples/rooftop_panels.toml)",
            UserFile::Camera => "Camera file (examples/cameras/)",
        }
    }
}

const HEADER: &str = "# File keys\n\n\
Every key of the files a user writes, generated from the parsers' own definitions by \
`polarimeter plan schema --markdown`; `polarimeter plan schema --file plan|rig|scene|camera` \
prints each as a JSON Schema (for editors). A test fails when this file and the code \
disagree. A key without a default must be given; a section marked optional may be left out. A \
plan's `kind` chooses which one of the kinds' sections it has.\n";

/// `docs/FILE-KEYS.md`: each file's keys, one table per section.
pub fn file_keys_markdown() -> String {
    let mut out = String::from(HEADER);
    for f in UserFile::ALL {
        out.push_str(&format!("\n## {}\n", f.title()));
        out.push_str(&polar_engine::plan_schema::keys_markdown(
            &f.schema(),
            "###",
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `docs/FILE-KEYS.md` is what the code generates: a key added, renamed, documented
    /// differently or given another default in any of the four files' types changes the
    /// generated text, and this test names the first line that differs (regenerate with
    /// `polarimeter plan schema --markdown > docs/FILE-KEYS.md`).
    #[test]
    fn file_keys_reference_is_current() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../docs/FILE-KEYS.md");
        let written = std::fs::read_to_string(path).unwrap_or_default();
        let generated = file_keys_markdown();
        if written != generated {
            let line = written
                .lines()
                .zip(generated.lines())
                .position(|(a, b)| a != b)
                .unwrap_or(written.lines().count().min(generated.lines().count()));
            panic!(
                "docs/FILE-KEYS.md differs from the code at line {}: written {:?}, generated \
                 {:?}; regenerate with `polarimeter plan schema --markdown > docs/FILE-KEYS.md`",
                line + 1,
                written.lines().nth(line),
                generated.lines().nth(line)
            );
        }
    }

    /// Each file's schema has the sections its parser reads: the rig file's `[stage]` and
    /// `[camera]`, the scene's `[sun]`, `[band]`, `[sensor]` and its `material` list, the
    /// camera file's top-level keys (a camera with no `name` would not parse).
    #[test]
    fn every_file_has_its_sections() {
        let has = |f: UserFile, key: &str| f.schema()["properties"].get(key).is_some();
        for key in ["stage", "camera"] {
            assert!(has(UserFile::Rig, key), "rig {key}");
        }
        for key in ["sun", "band", "sensor", "material", "atmosphere"] {
            assert!(has(UserFile::Scene, key), "scene {key}");
        }
        assert!(has(UserFile::Camera, "name"), "camera name");
        let md = file_keys_markdown();
        for f in UserFile::ALL {
            assert!(md.contains(&format!("## {}", f.title())), "{f:?}");
        }
    }
}
