//! `polarimeter simulate photon-transfer` and `polarimeter calibrate noise` end to end: frames
//! simulated from the shipped camera files (known truth) are calibrated back by EMVA 1288 photon
//! transfer, and broken frame directories give errors naming the file.
//!
//! Frame size: 256 x 256 pixels. The relative standard error of one pair's temporal variance is
//! sqrt(2 / n) = 0.55 % for n = 65536; the photon-transfer fit over the ~14 points of the linear
//! range brings K to about 0.15 % and the read noise (dark variance extrapolated to zero
//! exposure, over 26 dark pairs) to about 0.2 % (the reported standard uncertainties), so the
//! required 1 % is more than 4 standard uncertainties.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use polar_cli::calibrate::{
    calibrate_noise, sim_frames, CalibrateError, NoiseOptions, NoiseReport, SimFramesOptions,
};
use polar_model::calibration::Estimate;
use polar_model::sensor::Camera;
use std::path::{Path, PathBuf};
use std::process::Command;

/// A unique temporary directory, removed when dropped (also when a test fails).
struct TempDir(PathBuf);

impl TempDir {
    fn new(name: &str) -> TempDir {
        let dir = std::env::temp_dir().join(format!(
            "polar-calibrate-{}-{name}-{}",
            std::process::id(),
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap()
                .as_nanos()
        ));
        std::fs::create_dir_all(&dir).unwrap();
        TempDir(dir)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn camera_path(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../examples/cameras")
        .join(format!("{name}.toml"))
}

fn camera(name: &str) -> Camera {
    Camera::from_toml_str(&std::fs::read_to_string(camera_path(name)).unwrap()).unwrap()
}

/// Simulates a 256 x 256 series with 1 % PRNU and 2 DN DSNU (which the pair differences must
/// cancel: at 7000 e- the PRNU's spatial variance is half the temporal one).
fn simulate(name: &str, dir: &Path, seed: u64) {
    let opts = SimFramesOptions {
        width: 256,
        height: 256,
        prnu: 0.01,
        dsnu_dn: 2.0,
        seed,
        ..SimFramesOptions::new(camera_path(name), dir.to_path_buf())
    };
    let summary = sim_frames(&opts).unwrap();
    assert_eq!(summary.frames, 4 * summary.exposure_points);
}

fn rel(e: Estimate, truth: f64) -> f64 {
    e.value / truth - 1.0
}

/// The tolerances, with their reasons:
///
/// * K and read noise: 1 % (the requirement; the standard uncertainties are ~0.15-0.2 %).
/// * QE: 1 % (R from the pair means is far more precise than K, so QE inherits K's ~0.15 %).
/// * Dark current: `dark_tol` (0.2 % standard uncertainty for the CMOS at 3 e-/s over 1.37 s; the
///   CCD's 1 e-/s at K = 0.1 is only 0.14 DN over the series against a dark mean's standard error
///   of 0.003 DN, 1.6-1.9 %), and within 4 reported standard uncertainties.
/// * Offset: 0.01 DN (standard uncertainty 0.0012 DN: sigma_dark / sqrt(2 n) per pair).
/// * Saturation capacity: 0 to 6 % below the clip `min(full_well, (2^bits - 1 - b) / K)`:
///   EMVA 1288 puts saturation at the exposure of largest variance, which lies below the clip by
///   a few sigma of shot noise and PRNU (100 e- each at 10000 e-: 2-3 %), and the exposure grid's
///   step there is 2 % of the capacity.
fn check_recovery(name: &str, report: &NoiseReport, dark_tol: f64) -> [f64; 6] {
    let cam = camera(name);
    let r = &report.result;
    let k = rel(r.k_dn_per_e, cam.gain_dn_per_e);
    let sd = rel(r.read_noise_e, cam.read_noise_e);
    let dc_est = r.dark_current_e_per_s.expect("dark current");
    let dc = rel(dc_est, cam.dark_current_e_per_s);
    let off = r.offset_dn.value - cam.offset_dn;
    let clip_e = cam
        .full_well_e
        .min((cam.adc_max_dn() - cam.offset_dn) / cam.gain_dn_per_e);
    let sat = rel(r.saturation_capacity_e, clip_e);
    let qe = rel(r.qe.expect("qe"), cam.qe_at(550.0));
    eprintln!(
        "{name}: K {:+.3} %, read noise {:+.3} %, dark current {:+.3} %, offset {off:+.4} DN, \
         saturation {:+.2} %, QE {:+.3} %",
        100.0 * k,
        100.0 * sd,
        100.0 * dc,
        100.0 * sat,
        100.0 * qe
    );
    assert!(k.abs() < 0.01, "{name}: K {:?}", r.k_dn_per_e);
    assert!(sd.abs() < 0.01, "{name}: read noise {:?}", r.read_noise_e);
    assert!(!r.read_noise_is_upper_limit);
    assert!(qe.abs() < 0.01, "{name}: QE {:?}", r.qe);
    assert!(dc.abs() < dark_tol, "{name}: dark current {dc_est:?}");
    assert!(
        (dc_est.value - cam.dark_current_e_per_s).abs() < 4.0 * dc_est.uncertainty,
        "{name}: dark current {dc_est:?}"
    );
    assert!(off.abs() < 0.01, "{name}: offset {:?}", r.offset_dn);
    assert!((-0.06..=0.0).contains(&sat), "{name}: saturation {sat}");
    assert!(r.warnings.is_empty(), "{name}: {:?}", r.warnings);
    [k, sd, dc, off, sat, qe]
}

/// The CMOS (K = 0.35, sigma_d = 2.5 e-, 3 e-/s, b = 16, full well 10000 e-) through the library,
/// then the same frames through the binary with a base camera: the JSON has every field, the
/// camera.toml parses and carries the measured K, and the PNG and noise.toml are written.
#[test]
fn cmos_truth_is_recovered_and_the_binary_agrees() {
    let tmp = TempDir::new("cmos");
    let frames = tmp.0.join("frames");
    simulate("cmos_modern", &frames, 1);
    let report = calibrate_noise(&NoiseOptions {
        frames: frames.clone(),
        out: Some(tmp.0.join("lib")),
        base_camera: None,
    })
    .unwrap();
    check_recovery("cmos_modern", &report, 0.02);
    assert_eq!(report.result.points.len(), 26);

    let out = tmp.0.join("bin");
    let run = Command::new(env!("CARGO_BIN_EXE_polarimeter"))
        .args(["calibrate", "noise", "--frames"])
        .arg(&frames)
        .arg("--out")
        .arg(&out)
        .arg("--base-camera")
        .arg(camera_path("cmos_modern"))
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
    let cam = camera("cmos_modern");
    for (field, truth) in [
        ("k_dn_per_e", cam.gain_dn_per_e),
        ("read_noise_e", cam.read_noise_e),
    ] {
        let value = v[field]["value"].as_f64().unwrap();
        assert!((value / truth - 1.0).abs() < 0.01, "{field}: {value}");
        assert!(v[field]["uncertainty"].as_f64().unwrap() > 0.0);
    }
    for field in [
        "dark_current_e_per_s",
        "offset_dn",
        "saturation_capacity_e",
        "qe",
    ] {
        assert!(v[field]["value"].is_f64(), "{field}: {}", v[field]);
        assert!(v[field]["uncertainty"].is_f64(), "{field}");
    }
    assert_eq!(
        v["linear_range"]["points"],
        report.result.linear_range.points
    );
    assert_eq!(v["points"].as_array().unwrap().len(), 26);
    let written =
        Camera::from_toml_str(&std::fs::read_to_string(out.join("camera.toml")).unwrap()).unwrap();
    assert_eq!(
        written.gain_dn_per_e,
        v["k_dn_per_e"]["value"].as_f64().unwrap()
    );
    assert_eq!(
        written.full_well_e,
        v["saturation_capacity_e"]["value"].as_f64().unwrap()
    );
    assert_eq!(written.qe, cam.qe);
    let png = std::fs::read(out.join("photon_transfer.png")).unwrap();
    assert!(png.starts_with(b"\x89PNG") && png.len() > 10_000);
    let noise = std::fs::read_to_string(out.join("noise.toml")).unwrap();
    assert!(noise.contains("gain_dn_per_e = ") && noise.contains("[uncertainty]"));
}

/// The cooled CCD (K = 0.1, sigma_d = 10 e-, 1 e-/s, b = 100, 12-bit: the ADC clips at 39950 e-
/// before the 40000 e- full well).
#[test]
fn ccd_truth_is_recovered() {
    let tmp = TempDir::new("ccd");
    simulate("ccd_seed", &tmp.0, 2);
    let report = calibrate_noise(&NoiseOptions {
        frames: tmp.0.clone(),
        out: None,
        base_camera: None,
    })
    .unwrap();
    check_recovery("ccd_seed", &report, 0.08);
    assert!(tmp.0.join("photon_transfer.png").is_file());
}

/// A small series through the binary: frames.csv lists two flats and two darks per exposure
/// point (5 plus the 6 near and past saturation), and the same seed gives the same frames.
#[test]
fn sim_frames_through_the_binary_is_deterministic() {
    let tmp = TempDir::new("sim");
    let run = |dir: &Path| {
        let out = Command::new(env!("CARGO_BIN_EXE_polarimeter"))
            .args(["simulate", "photon-transfer", "--camera"])
            .arg(camera_path("ccd_seed"))
            .arg("--out")
            .arg(dir)
            .args(["--width", "32", "--height", "16", "--exposures", "5"])
            .args(["--prnu", "0.01", "--dsnu-dn", "1", "--seed", "7"])
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        serde_json::from_slice::<serde_json::Value>(&out.stdout).unwrap()
    };
    let (a, b) = (tmp.0.join("a"), tmp.0.join("b"));
    let summary = run(&a);
    run(&b);
    assert_eq!(summary["exposure_points"], 11);
    let csv = std::fs::read_to_string(a.join("frames.csv")).unwrap();
    assert_eq!(csv.lines().count(), 1 + 44);
    for line in csv.lines().skip(1) {
        let file = line.split(',').next().unwrap();
        assert_eq!(
            std::fs::read(a.join(file)).unwrap(),
            std::fs::read(b.join(file)).unwrap(),
            "{file}"
        );
    }
    let bad = Command::new(env!("CARGO_BIN_EXE_polarimeter"))
        .args(["simulate", "photon-transfer", "--camera"])
        .arg(camera_path("ccd_seed"))
        .arg("--out")
        .arg(tmp.0.join("c"))
        .args(["--max-fill", "3"])
        .output()
        .unwrap();
    assert_eq!(bad.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&bad.stderr).contains("--max-fill = 3"));
}

fn error_of(dir: &Path) -> String {
    let err: CalibrateError = calibrate_noise(&NoiseOptions {
        frames: dir.to_path_buf(),
        out: None,
        base_camera: None,
    })
    .unwrap_err();
    err.to_string()
}

/// Broken directories: each error names the file (and frames.csv's row): a TIFF listed but
/// missing, an 8-bit TIFF, no frames.csv, a bad kind, a lone flat; and the binary exits 2 with
/// the file named on stderr.
#[test]
fn errors_name_the_file() {
    let tmp = TempDir::new("errors");
    let good = tmp.0.join("good");
    let opts = SimFramesOptions {
        width: 32,
        height: 32,
        exposures: 5,
        ..SimFramesOptions::new(camera_path("cmos_modern"), good.clone())
    };
    sim_frames(&opts).unwrap();
    let copy = |name: &str| {
        let dir = tmp.0.join(name);
        std::fs::create_dir_all(&dir).unwrap();
        for entry in std::fs::read_dir(&good).unwrap() {
            let entry = entry.unwrap();
            std::fs::copy(entry.path(), dir.join(entry.file_name())).unwrap();
        }
        dir
    };
    // frames.csv rows per exposure point: flat a, flat b, dark a, dark b (row 3: dark_001_a).
    let missing = copy("missing");
    std::fs::remove_file(missing.join("dark_001_a.tif")).unwrap();
    let e = error_of(&missing);
    assert!(
        e.contains("dark_001_a.tif") && e.contains("row 3") && e.contains("not found"),
        "{e}"
    );

    let eight = copy("eight");
    let path = eight.join("flat_002_b.tif");
    let mut w = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
    tiff::encoder::TiffEncoder::new(&mut w)
        .unwrap()
        .write_image::<tiff::encoder::colortype::Gray8>(32, 32, &[7u8; 1024])
        .unwrap();
    drop(w);
    let e = error_of(&eight);
    assert!(
        e.contains("flat_002_b.tif") && e.contains("row 6") && e.contains("8-bit"),
        "{e}"
    );

    let no_csv = copy("no_csv");
    std::fs::remove_file(no_csv.join("frames.csv")).unwrap();
    let e = error_of(&no_csv);
    assert!(e.contains("frames.csv") && e.contains("not found"), "{e}");

    let kind = copy("kind");
    let csv = std::fs::read_to_string(kind.join("frames.csv")).unwrap();
    let csv: String = csv
        .lines()
        .map(|l| {
            if l.starts_with("dark_003_a.tif,") {
                l.replace(",dark,", ",bright,")
            } else {
                l.to_string()
            }
        })
        .map(|l| format!("{l}\n"))
        .collect();
    std::fs::write(kind.join("frames.csv"), csv).unwrap();
    let e = error_of(&kind);
    assert!(
        e.contains("dark_003_a.tif") && e.contains("\"bright\"") && e.contains("row 11"),
        "{e}"
    );

    let lone = copy("lone");
    let csv = std::fs::read_to_string(lone.join("frames.csv")).unwrap();
    let csv: String = csv
        .lines()
        .filter(|l| !l.starts_with("flat_004_b.tif"))
        .map(|l| format!("{l}\n"))
        .collect();
    std::fs::write(lone.join("frames.csv"), csv).unwrap();
    let e = error_of(&lone);
    assert!(
        e.contains("flat_004_a.tif") && e.contains("at least two"),
        "{e}"
    );

    let run = Command::new(env!("CARGO_BIN_EXE_polarimeter"))
        .args(["calibrate", "noise", "--frames"])
        .arg(&eight)
        .output()
        .unwrap();
    assert_eq!(run.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        stderr.contains("flat_002_b.tif") && stderr.contains("8-bit"),
        "{stderr}"
    );
}
