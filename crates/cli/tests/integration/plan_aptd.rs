//! `analyze aptd --frames DIR`: APTD offline over a stack of 16-bit TIFFs at 12 analyzer angles.
#![allow(clippy::unwrap_used)] // test helpers outside #[test] functions

use nalgebra::{Matrix3, Vector3};
use polar_planner::scr::row;
use polar_planner::Contrast;
use std::process::Command;

/// A 64x64 scene: correlated background clutter, an 8x8 target, Gaussian frame noise of
/// variance 80 DN^2; frames every 15 deg written as TIFFs with frames.csv.
fn write_stack(dir: &std::path::Path) -> (Contrast, Vec<f64>) {
    std::fs::create_dir_all(dir).unwrap();
    let sigma_b = Matrix3::new(400.0, 30.0, -20.0, 30.0, 60.0, 12.0, -20.0, 12.0, 45.0);
    let d = Vector3::new(40.0, 30.0, -12.0);
    let noise_var = 80.0f64;
    let l = sigma_b.cholesky().unwrap().l();
    let mut state = 0x2545_F491_4F6C_DD1Du64;
    let mut normal = move || {
        let mut u = || {
            state ^= state >> 12;
            state ^= state << 25;
            state ^= state >> 27;
            ((state.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let (a, b) = (u(), u());
        (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
    };
    let mu_b = Vector3::new(2000.0, 50.0, -20.0);
    let mut stokes = Vec::new();
    for y in 0..64 {
        for x in 0..64 {
            let inside = (20..28).contains(&x) && (30..38).contains(&y);
            let z = Vector3::new(normal(), normal(), normal());
            stokes.push(mu_b + l * z + if inside { d } else { Vector3::zeros() });
        }
    }
    let mut csv = String::from("file,angle_deg\n");
    let angles: Vec<f64> = (0..12).map(|k| 15.0 * k as f64).collect();
    for (k, deg) in angles.iter().enumerate() {
        let w = row(deg.to_radians());
        let px: Vec<u16> = stokes
            .iter()
            .map(|s| {
                (w.dot(s) + noise_var.sqrt() * normal())
                    .round()
                    .clamp(0.0, 65535.0) as u16
            })
            .collect();
        let name = format!("f{k:02}.tif");
        polar_cli::calibrate::write_tiff(&dir.join(&name), 64, 64, &px).unwrap();
        csv.push_str(&format!("{name},{deg}\n"));
    }
    std::fs::write(dir.join("frames.csv"), csv).unwrap();
    (Contrast::new(d, sigma_b, noise_var).unwrap(), angles)
}

/// From 0/60/120, with the target region known, the loop picks sets among the stack's angles
/// whose SCR under the true statistics beats 0/60/120 and is within 5 % of the best 3-subset
/// of the stack's angles (brute force; sampling error of the estimates from 64 target pixels).
/// It records its decisions, and the matched filter on the final Stokes image detects more
/// than half the target at an empirical Pfa of 1e-2. A missing frames.csv is named.
#[test]
fn offline_aptd_over_a_stack() {
    let dir = std::env::temp_dir().join(format!("polar-aptd-stack-{}", std::process::id()));
    let (truth, angles) = write_stack(&dir);
    let out = Command::new(env!("CARGO_BIN_EXE_polarimeter"))
        .args([
            "analyze",
            "aptd",
            "--frames",
            dir.to_str().unwrap(),
            "--noise-var",
            "80",
            "--target-region",
            "20,30,28,38",
            "--pfa",
            "1e-2",
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let chosen: Vec<f64> = v["angles_deg"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a.as_f64().unwrap())
        .collect();
    assert_eq!(chosen.len(), 3);
    for a in &chosen {
        assert!(
            angles.iter().any(|b| (a - b).abs() < 1e-6),
            "{a} is not a stack angle"
        );
    }
    let rad = |v: &[f64]| v.iter().map(|d| d.to_radians()).collect::<Vec<_>>();
    let scr = truth.scr(&rad(&chosen));
    let mut best = 0.0f64;
    for i in 0..12 {
        for j in i + 1..12 {
            for k in j + 1..12 {
                best = best.max(truth.scr(&rad(&[angles[i], angles[j], angles[k]])));
            }
        }
    }
    println!(
        "chosen {chosen:?}: true SCR {scr:.4}, best subset {best:.4}, 0/60/120 {:.4}, detection {}",
        truth.scr(&rad(&[0.0, 60.0, 120.0])),
        v["detection"]
    );
    assert!(scr > truth.scr(&rad(&[0.0, 60.0, 120.0])), "{chosen:?}");
    assert!(scr >= 0.95 * best, "{scr} vs best subset {best}");
    assert!(!v["decisions"].as_array().unwrap().is_empty());
    assert!(
        v["detection"]["pd_matched_filter"].as_f64().unwrap() > 0.5,
        "{}",
        v["detection"]
    );
    let _ = std::fs::remove_dir_all(&dir);

    let out = Command::new(env!("CARGO_BIN_EXE_polarimeter"))
        .args([
            "analyze",
            "aptd",
            "--frames",
            "/nonexistent-stack",
            "--noise-var",
            "80",
        ])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent-stack/frames.csv"));
}
