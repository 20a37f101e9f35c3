//! `polarimeter report study fov` (Meng (2012) Sec. 4.2.3, Table 4.2) through the library on
//! examples/study.toml: the geometry variation grows with the field of view.
#![allow(clippy::unwrap_used)] // tests panic on failure by design

use polar_cli::commands::load_scene;
use polar_cli::study::{Study, StudySettings};
use polar_cli::study_fov::{run, SIGMAS};
use polar_model::sensor::Camera;
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The DoLP spread from the geometry alone grows with the field of view for every class and
/// roughness: a wider field spans more sun-surface-sensor geometries (Meng (2012) Sec. 3.1.5).
/// Between 1 and 10 degrees it grows by more than 3 times (to first order the spread is
/// proportional to the angular extent, 10 times here; the factor 3 leaves room for the
/// curvature of DoLP over the field and the scene model's tile error); the S0 spread grows
/// likewise; and every row's total DoLP spread (geometry, texture and sensor noise) is at
/// least the geometry's alone (to 1e-9 relative: the variances add).
#[test]
fn geometry_spread_grows_with_the_field_of_view() {
    let scene = load_scene(&root().join("examples/study.toml")).unwrap();
    let text = std::fs::read_to_string(root().join("examples/cameras/ccd_seed.toml")).unwrap();
    let camera = Camera::from_toml_str(&text).unwrap();
    let study = Study::new(
        &scene,
        "examples/study.toml",
        &camera,
        StudySettings::default(),
    )
    .unwrap();
    let rows = run(&study, &[1.0, 10.0]).unwrap();
    assert_eq!(rows.len(), 2 * 3 * SIGMAS.len());
    for &sigma in &SIGMAS {
        for class in ["black_paint", "glass", "asphalt"] {
            let at = |fov: f64| {
                rows.iter()
                    .find(|r| r.class == class && r.sigma == sigma && r.fov_deg == fov)
                    .unwrap()
            };
            let (narrow, wide) = (at(1.0), at(10.0));
            assert!(
                wide.dolp_std_geometry > 3.0 * narrow.dolp_std_geometry,
                "{class} sigma {sigma}: {} -> {}",
                narrow.dolp_std_geometry,
                wide.dolp_std_geometry
            );
            assert!(
                wide.s0_rel_std_geometry > 3.0 * narrow.s0_rel_std_geometry,
                "{class} sigma {sigma}: {} -> {}",
                narrow.s0_rel_std_geometry,
                wide.s0_rel_std_geometry
            );
        }
    }
    for r in &rows {
        assert!(
            r.dolp_std_total >= r.dolp_std_geometry * (1.0 - 1e-9),
            "{r:?}"
        );
        if r.class != "asphalt" {
            assert!(r.pd_dolp.is_some_and(|p| (0.0..=1.0).contains(&p)), "{r:?}");
            assert!(!r.roc.is_empty());
        }
    }
}
