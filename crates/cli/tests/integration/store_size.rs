//! The disk a run takes: `plan check`'s `store.bytes` forecast against the store a simulated
//! run of the example plan writes, and the store against its raw frames, with the default
//! `[storage]` (zstd, the essential products at the precision their sigma warrants).
#![allow(clippy::unwrap_used)]

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

const BIN: &str = env!("CARGO_BIN_EXE_polarimeter");

fn examples() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../examples/plans")
}

fn bytes_under(dir: &Path) -> u64 {
    std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .map(|e| {
            if e.file_type().unwrap().is_dir() {
                bytes_under(&e.path())
            } else {
                e.metadata().unwrap().len()
            }
        })
        .sum()
}

fn json_of(out: &std::process::Output) -> Value {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    serde_json::from_str(text.lines().last().unwrap()).unwrap()
}

/// Runs `plan` on the simulated rig; (forecast bytes, store bytes, raw frame bytes).
fn forecast_and_store(plan: &str) -> (u64, u64, u64) {
    let plan = examples().join(plan);
    let check = Command::new(BIN)
        .args(["plan", "check", plan.to_str().unwrap()])
        .stdin(Stdio::null())
        .output()
        .unwrap();
    let check = json_of(&check);
    let forecast = check["store"]["bytes"].as_u64().unwrap();
    let tmp = std::env::temp_dir().join(format!(
        "polar-store-size-{}-{}",
        std::process::id(),
        plan.file_stem().unwrap().to_string_lossy()
    ));
    let _ = std::fs::remove_dir_all(&tmp);
    let run = Command::new(BIN)
        .args([
            "acquire",
            "run",
            plan.to_str().unwrap(),
            "--simulate",
            "--out",
        ])
        .arg(&tmp)
        .stdin(Stdio::null())
        .output()
        .unwrap();
    let run = json_of(&run);
    assert_eq!(run["state"], "done", "{run}");
    let store = bytes_under(&tmp.join("run.zarr"));
    let frames = run["summary"]["frames_stored"].as_u64().unwrap();
    let raw = frames * 160 * 120 * 2;
    let _ = std::fs::remove_dir_all(&tmp);
    (forecast, store, raw)
}

#[test]
fn forecast_bytes_match_the_store_and_the_store_stays_near_its_raw_frames() {
    // capture.toml: 4 darks and 3 sets of 4 angles; continuous.toml: 20 half turns of 4
    // spans. Both at the example plans' 160x120.
    for plan in ["capture.toml", "continuous.toml"] {
        let (forecast, store, raw) = forecast_and_store(plan);
        let off = forecast as f64 / store as f64 - 1.0;
        let ratio = store as f64 / raw as f64;
        println!("{plan}: forecast {forecast} B, store {store} B ({off:+.3}), raw frames {raw} B, store/raw {ratio:.3}");
        // The forecast stores one set of the same scene's frames with other noise draws: the
        // compressed sizes differ by the noise's and the scene's spread between sets, a few
        // per cent.
        assert!(off.abs() <= 0.05, "{plan}: forecast off by {off:+.3}");
        // Frames zstd-compressed (lossless) and the essential products rounded to their
        // sigma: at most 1.5x the raw frames (it was 5.8x uncompressed with every plane).
        assert!(ratio <= 1.5, "{plan}: store/raw {ratio:.3}");
    }
}
