//! The documents' tables of dialects and camera backends against the registries they describe,
//! so a dialect or backend added to a registry and left out of the documents fails here.

use polar_drivers::registry::DIALECTS;
use polar_rig::camera::CAMERA_BACKENDS;

fn read(path: &str) -> String {
    let p = polar_hil_tests::repo_root().join(path);
    std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// ARCHITECTURE.md's "Each device" table has one row per registered dialect naming the dialect,
/// each of its models, its driver's file and its simulator's file; docs/DEVICES.md has a section
/// heading per dialect that names its models (our firmware's: section 2).
#[test]
fn device_tables_list_every_dialect() {
    let architecture = read("ARCHITECTURE.md");
    let devices = read("docs/DEVICES.md");
    for d in DIALECTS {
        let driver = format!("`crates/drivers/src/{}.rs`", d.name);
        let row = architecture
            .lines()
            .find(|l| l.starts_with('|') && l.contains(&driver))
            .unwrap_or_else(|| panic!("ARCHITECTURE.md: no device row names {driver}"));
        let simulator = format!("`hil-mocks/src/{}.rs`", d.name);
        let name = format!("(`{}`)", d.name);
        assert!(row.contains(&simulator) && row.contains(&name), "{row}");
        let lower = row.to_lowercase();
        for m in d.models {
            assert!(
                lower.contains(m),
                "ARCHITECTURE.md's row lacks the model {m}: {row}"
            );
        }
        if d.name == "native" {
            assert!(devices.contains("## 2. Our stage firmware"));
            continue;
        }
        let heading = devices
            .lines()
            .filter(|l| l.starts_with("### 1."))
            .find(|l| d.models.iter().all(|m| l.to_lowercase().contains(m)));
        assert!(
            heading.is_some(),
            "docs/DEVICES.md: no section heading names all of {:?}",
            d.models
        );
    }
}

/// docs/DEVICES.md's camera section and the README name every camera backend of the registry
/// with its cargo feature.
#[test]
fn camera_docs_list_every_backend() {
    let devices = read("docs/DEVICES.md");
    let readme = read("README.md");
    for b in CAMERA_BACKENDS {
        let named = format!("`{}`", b.name);
        assert!(
            devices.contains(&named),
            "docs/DEVICES.md does not name {named}"
        );
        assert!(
            readme.contains(b.name),
            "README.md does not name {}",
            b.name
        );
    }
}
