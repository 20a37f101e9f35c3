//! The harness of the public-client conformance tests (`tests/hil/conformance_*.rs`): the
//! clients' python, whether it has the clients, and one run of a `scripts/conformance/*.py`
//! script with the rows of its results.

use crate::repo_root;
use std::path::{Path, PathBuf};
use std::process::Command;

/// The venv's python: `POLARIMETER_PYTHON`, else `target/py-venv/bin/python` (the venv
/// `scripts/test.sh` creates from `scripts/requirements.txt`).
pub fn client_python() -> PathBuf {
    std::env::var_os("POLARIMETER_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo_root().join("target/py-venv/bin/python"))
}

/// Whether `python` runs `import IMPORTS`. When it does not: `false` (the test is skipped,
/// saying why) with `POLARIMETER_SKIP_PYTHON=1`, else a panic saying how to get the clients.
pub fn clients_available(python: &Path, imports: &str) -> bool {
    let ok = Command::new(python)
        .args(["-c", &format!("import {imports}")])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if ok {
        return true;
    }
    if std::env::var("POLARIMETER_SKIP_PYTHON").as_deref() == Ok("1") {
        println!("skipped: {} cannot import {imports}", python.display());
        return false;
    }
    panic!(
        "{} cannot import {imports}: run `bash scripts/test.sh`, which creates the venv, or \
         point POLARIMETER_PYTHON at a python that has them; set POLARIMETER_SKIP_PYTHON=1 to \
         skip this test",
        python.display()
    );
}

/// What a conformance script reported.
#[derive(Debug)]
pub struct ScriptRun {
    /// Its results, one row per cell: client, device, operation, status, detail.
    pub rows: Vec<Vec<String>>,
    /// Its stderr.
    pub log: String,
    /// Whether it exited 0.
    pub success: bool,
}

impl ScriptRun {
    /// Every row has its five fields and a status in `allowed`; a row that did not pass says
    /// why.
    pub fn check_rows(&self, allowed: &[&str]) {
        assert!(!self.rows.is_empty(), "no results:\n{}", self.log);
        for r in &self.rows {
            assert!(r.len() >= 5, "a row has 5 fields: {r:?}");
            assert!(allowed.contains(&r[3].as_str()), "{r:?}\n{}", self.log);
            if r[3] != "passed" {
                assert!(!r[4].is_empty(), "a {} without its reason: {r:?}", r[3]);
            }
        }
        assert!(self.success, "the script failed:\n{}", self.log);
    }
}

/// Runs `scripts/conformance/SCRIPT ARGS --results DIR/results.tsv` with `python` under a
/// 300 s limit (blocking: call it from `spawn_blocking`), prints its table and log, and writes
/// the table to `target/TABLE_FILE`.
pub fn run_script(
    python: &Path,
    script: &str,
    args: &[String],
    dir: &Path,
    table_file: &str,
) -> ScriptRun {
    let results = dir.join("results.tsv");
    let output = Command::new("timeout")
        .arg("300")
        .arg(python)
        .arg(repo_root().join("scripts/conformance").join(script))
        .args(args)
        .arg("--results")
        .arg(&results)
        .output()
        .expect("run the conformance script");
    let table = String::from_utf8_lossy(&output.stdout).into_owned();
    let log = String::from_utf8_lossy(&output.stderr).into_owned();
    println!("{table}\n{log}");
    let _ = std::fs::write(repo_root().join("target").join(table_file), &table);
    let text = std::fs::read_to_string(&results).unwrap_or_default();
    let rows = text
        .lines()
        .filter(|l| !l.is_empty())
        .map(|l| l.split('\t').map(str::to_string).collect())
        .collect();
    ScriptRun {
        rows,
        log,
        success: output.status.success(),
    }
}
