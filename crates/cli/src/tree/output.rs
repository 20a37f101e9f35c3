//! How a command's result reaches the user: JSON, text, files or a run's summary on stdout, and
//! `error: ...` on stderr with the exit status (2 for a refused input, 1 for a failure).

use super::errors::Worded;
use polar_cli::commands::CommandError;
use polar_cli::devices;
use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

/// The exit status of a command that reports failures as `anyhow` errors: `error: ...` and 1.
pub fn status(result: anyhow::Result<ExitCode>) -> ExitCode {
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// Prints `error: MESSAGE` and returns exit status 2 (a refused input).
pub fn refused(message: impl std::fmt::Display) -> ExitCode {
    eprintln!("error: {message}");
    ExitCode::from(2)
}

/// Prints the files a command wrote, one per line, and returns 0; or prints `error: ...` and
/// returns 2.
pub fn print_files<E: Worded>(result: Result<Vec<PathBuf>, E>) -> ExitCode {
    match result {
        Ok(files) => {
            for f in files {
                println!("{}", f.display());
            }
            ExitCode::SUCCESS
        }
        Err(e) => refused(e.worded()),
    }
}

/// Prints a command's JSON on stdout (and its `warnings` on stderr) and returns exit status 0,
/// or prints `error: ...` on stderr and returns 2.
pub fn print_json<E: Worded>(result: Result<serde_json::Value, E>) -> ExitCode {
    match result {
        Ok(v) => {
            if let Some(w) = v.get("warnings").and_then(|w| w.as_array()) {
                for warning in w {
                    eprintln!("warning: {}", warning.as_str().unwrap_or_default());
                }
            }
            let mut out = std::io::stdout().lock();
            let ok = serde_json::to_writer(&mut out, &v).is_ok() && writeln!(out).is_ok();
            if ok {
                ExitCode::SUCCESS
            } else {
                ExitCode::FAILURE
            }
        }
        Err(e) => refused(e.worded()),
    }
}

/// Prints a command's text report and returns 0, or prints `error: ...` and returns 2.
pub fn print_text(result: Result<String, CommandError>) -> ExitCode {
    match result {
        Ok(text) => {
            print!("{text}");
            ExitCode::SUCCESS
        }
        Err(e) => refused(e.worded()),
    }
}

/// Prints a run's JSON and returns its exit status (0 done, 3 paused, 4 aborted), or prints
/// `error: ...` and returns 2.
pub fn print_run(result: Result<(serde_json::Value, i32), CommandError>) -> ExitCode {
    match result {
        Ok((v, code)) => {
            println!("{v}");
            ExitCode::from(u8::try_from(code).unwrap_or(1))
        }
        Err(e) => refused(e.worded()),
    }
}

/// Prints a device command's result (JSON with `--json`, else text) and returns 0, or prints
/// `error: ...` and returns 2.
pub fn print_device(
    result: Result<serde_json::Value, devices::DevicesError>,
    json: bool,
) -> ExitCode {
    match result {
        Ok(v) => {
            if json {
                println!("{v}");
            } else {
                print!("{}", devices::text(&v));
            }
            ExitCode::SUCCESS
        }
        Err(e) => refused(e.worded()),
    }
}
