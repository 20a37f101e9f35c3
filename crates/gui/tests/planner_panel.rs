//! The planner panel: the computation on the default scene (the optimum's SCR against the
//! conventional sets', the ROC curves' range and monotonicity), and the panel driven by its
//! labels with egui_kittest, headless.
#![allow(clippy::unwrap_used)]

use eframe::egui;
use egui_kittest::kittest::Queryable;
use egui_kittest::Harness;
use polar_gui::planner_panel::{compute, PlannerInputs, PlannerPanel, PlannerResult};

/// Relative tolerance of "the optimum is at least as good" (the optimiser converges to
/// 0.01 deg; SCR is flat at its maximum).
const REL_TOL: f64 = 1e-9;

fn check_rocs(r: &PlannerResult) {
    for row in &r.rows {
        assert!((0.0..=1.0).contains(&row.pd), "{}: Pd {}", row.name, row.pd);
        assert!(
            row.roc.len() > 10,
            "{}: {} ROC points",
            row.name,
            row.roc.len()
        );
        for p in &row.roc {
            assert!(p[0] > 0.0 && p[0] <= 1.0, "{}: Pfa {}", row.name, p[0]);
            assert!((0.0..=1.0).contains(&p[1]), "{}: Pd {}", row.name, p[1]);
        }
        for w in row.roc.windows(2) {
            assert!(w[1][0] > w[0][0], "{}: Pfa not increasing", row.name);
            assert!(
                w[1][1] >= w[0][1],
                "{}: Pd falls from {} to {} between Pfa {} and {}",
                row.name,
                w[0][1],
                w[1][1],
                w[0][0],
                w[1][0]
            );
        }
    }
}

/// The optimum maximises the SCR: no conventional set beats the optimum with as many angles
/// (and none beats the chosen optimum when it has at least as many angles as the set).
fn check_optimum(r: &PlannerResult) {
    let opt = r.optimum().unwrap();
    assert_eq!(opt.angles_deg.len(), r.inputs.channels);
    assert!(opt.scr > 0.0 && opt.scr.is_finite(), "{}", opt.scr);
    assert!(opt.scr <= r.scr_clutter_limit * (1.0 + REL_TOL));
    for row in r.rows.iter().filter(|row| !row.optimal) {
        assert!(
            row.scr <= row.scr_optimum_same_n * (1.0 + REL_TOL),
            "{}: SCR {} above the optimum with {} angles {}",
            row.name,
            row.scr,
            row.angles_deg.len(),
            row.scr_optimum_same_n
        );
        assert!(row.scr_relative <= 1.0 + REL_TOL, "{}", row.scr_relative);
        if row.angles_deg.len() <= r.inputs.channels {
            assert!(
                row.scr <= opt.scr * (1.0 + REL_TOL),
                "{}: SCR {} above the optimum {}",
                row.name,
                row.scr,
                opt.scr
            );
        }
    }
}

/// The defaults: the optimum of 3 angles against 0/45/90, 0/60/120 and 0/45/90/135.
#[test]
fn compute_defaults() {
    let inputs = PlannerInputs::default();
    let r = compute(&inputs).unwrap();
    let names: Vec<&str> = r.rows.iter().map(|row| row.name.as_str()).collect();
    assert_eq!(names, ["optimal 3", "0/45/90", "0/60/120", "0/45/90/135"]);
    check_optimum(&r);
    check_rocs(&r);
    for row in &r.rows {
        println!(
            "{:12} {:?} SCR {:.6} Pd {:.6} rel {:.6} (optimum same N {:.6})",
            row.name, row.angles_deg, row.scr, row.pd, row.scr_relative, row.scr_optimum_same_n
        );
    }
    println!(
        "clutter limit {:.6}, condition {:.3e}, V {:.3e}; notes {:?}",
        r.scr_clutter_limit, r.clutter_condition, r.noise_var_w2_m4_sr2, r.notes
    );
}

/// With 4 angles the optimum beats every conventional set, the 4-angle one included.
#[test]
fn compute_four_angles_beats_every_set() {
    let inputs = PlannerInputs {
        channels: 4,
        ..PlannerInputs::default()
    };
    let r = compute(&inputs).unwrap();
    check_optimum(&r);
    check_rocs(&r);
    let opt = r.optimum().unwrap().scr;
    for row in &r.rows {
        assert!(
            row.scr <= opt * (1.0 + REL_TOL),
            "{}: {} > {opt}",
            row.name,
            row.scr
        );
    }
}

/// The panel optimises the forecast it shows: every row's SCR is the matched filter's on the
/// camera model's frames (the planner's objective agrees with it to 1e-6 relative, else a
/// note says so), and the optimum is at least every conventional set with as many or fewer
/// angles under those same numbers, for 3 and 4 channels, at a short exposure (shot and read
/// noise matter, so the real analyzer rows and the angle-dependent noise change the answer)
/// and a long one, with and without a separation.
#[test]
fn optimal_under_the_forecast_it_shows() {
    for (exposure_us, channels, min_separation_deg) in
        [(5.0, 3, 30.0), (5.0, 4, 0.0), (2000.0, 3, 0.0)]
    {
        let inputs = PlannerInputs {
            exposure_us,
            channels,
            min_separation_deg,
            ..PlannerInputs::default()
        };
        let r = compute(&inputs).unwrap();
        assert!(
            !r.notes
                .iter()
                .any(|n| n.contains("differs from the planner")),
            "{inputs:?}: {:?}",
            r.notes
        );
        check_optimum(&r);
        let opt = r.optimum().unwrap().scr;
        for row in r.rows.iter().filter(|row| row.angles_deg.len() <= channels) {
            assert!(
                row.scr <= opt * (1.0 + REL_TOL),
                "{inputs:?} {}: {} > {opt}",
                row.name,
                row.scr
            );
        }
    }
}

/// Bad inputs are errors naming the field, never panics.
#[test]
fn compute_errors() {
    let bad_material = PlannerInputs {
        target: "unobtainium".into(),
        ..PlannerInputs::default()
    };
    let e = compute(&bad_material).unwrap_err();
    assert!(e.contains("target") && e.contains("asphalt"), "{e}");
    for inputs in [
        PlannerInputs {
            exposure_us: -1.0,
            ..PlannerInputs::default()
        },
        PlannerInputs {
            channels: 7,
            ..PlannerInputs::default()
        },
        PlannerInputs {
            pfa: 1.0,
            ..PlannerInputs::default()
        },
        PlannerInputs {
            exposure_us: f64::NAN,
            ..PlannerInputs::default()
        },
    ] {
        assert!(compute(&inputs).is_err(), "{inputs:?}");
    }
    // Six angles 40 degrees apart do not fit in 180: the planner's error, as text.
    let e = compute(&PlannerInputs {
        channels: 6,
        min_separation_deg: 40.0,
        ..PlannerInputs::default()
    })
    .unwrap_err();
    assert!(e.contains("min_separation_deg"), "{e}");
    // The same material twice: no contrast, SCR 0 and Pd = Pfa, said in the notes.
    let r = compute(&PlannerInputs {
        target: "asphalt".into(),
        ..PlannerInputs::default()
    })
    .unwrap();
    assert!(r.rows.iter().all(|row| row.scr == 0.0));
    assert!(
        r.notes.iter().any(|n| n.contains("no contrast")),
        "{:?}",
        r.notes
    );
}

/// A separation the conventional sets break: said in the notes; the 4-angle optimum does not
/// exist (4 x 50 deg > 180 deg), so that row's relative SCR is NaN and the notes say why.
#[test]
fn compute_wide_separation() {
    let r = compute(&PlannerInputs {
        min_separation_deg: 50.0,
        ..PlannerInputs::default()
    })
    .unwrap();
    check_rocs(&r);
    let opt = r.optimum().unwrap();
    assert_eq!(opt.angles_deg.len(), 3);
    assert!(
        r.notes
            .iter()
            .any(|n| n.starts_with("0/45/90 has angles 45.0 deg apart")),
        "{:?}",
        r.notes
    );
    let four = r.rows.iter().find(|row| row.name == "0/45/90/135").unwrap();
    assert!(four.scr_relative.is_nan());
    assert!(
        r.notes
            .iter()
            .any(|n| n.contains("no optimum with 4 angles")),
        "{:?}",
        r.notes
    );
    // 0/60/120 keeps the separation: the optimum beats it.
    let sixty = r.rows.iter().find(|row| row.name == "0/60/120").unwrap();
    assert!(sixty.scr <= opt.scr * (1.0 + REL_TOL));
}

/// A plan's planner inputs are taken; a bad plan changes nothing.
#[test]
fn plan_text_inputs() {
    let mut p = PlannerPanel::new();
    p.set_plan_text(
        r#"name = "p"
kind = "capture"
[capture]
from_planner = { target = "metal", background = "grass", channels = 4, min_separation_deg = 20 }
exposure_us = [400]
"#,
    );
    let i = p.inputs();
    assert_eq!(
        (i.target.as_str(), i.background.as_str()),
        ("metal", "grass")
    );
    assert_eq!((i.channels, i.exposure_us), (4, 400.0));
    assert_eq!(i.min_separation_deg, 20.0);
    let before = p.inputs().clone();
    p.set_plan_text("kind = \"nonsense\"");
    assert_eq!(p.inputs(), &before);
}

/// The panel computes on its first frame, and again when Compute is clicked; the table shows
/// the optimum's row and the ROC plot is drawn.
#[test]
fn panel_compute_button() {
    let mut h = Harness::builder()
        .with_size(egui::vec2(1000.0, 1000.0))
        .build_ui_state(|ui, p: &mut PlannerPanel| p.show(ui), PlannerPanel::new());
    h.run();
    assert!(h.state().result().is_some(), "{:?}", h.state().error());
    h.get_by_label("Compute").click();
    h.run();
    let r = h.state().result().unwrap();
    assert_eq!(r.rows[0].name, "optimal 3");
    assert!(h.query_all_by_label_contains("optimal 3").next().is_some());
    assert!(h.query_all_by_label_contains("0/60/120").next().is_some());
    assert!(h
        .query_all_by_label_contains("SCR / optimum")
        .next()
        .is_some());
    assert!(h.state().error().is_none());
}
