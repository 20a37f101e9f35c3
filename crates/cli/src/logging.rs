//! `tracing` for the command: warnings (or more with `-v`, `-vv`) on stderr, and every
//! run's own log file, `RUN_DIR/run.log`, at info level with spans per step and device
//! operation.

use std::fs::File;
use std::io::Write;
use std::path::Path;
use std::sync::Mutex;
use tracing_subscriber::filter::LevelFilter;
use tracing_subscriber::fmt::MakeWriter;
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;
use tracing_subscriber::Layer;

static RUN_LOG: Mutex<Option<File>> = Mutex::new(None);

/// Writes to the current run's log file, if one is open.
#[derive(Debug, Clone, Copy)]
pub struct RunLogWriter;

impl Write for RunLogWriter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        if let Ok(mut g) = RUN_LOG.lock() {
            if let Some(f) = g.as_mut() {
                return f.write(buf);
            }
        }
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        if let Ok(mut g) = RUN_LOG.lock() {
            if let Some(f) = g.as_mut() {
                return f.flush();
            }
        }
        Ok(())
    }
}

impl<'a> MakeWriter<'a> for RunLogWriter {
    type Writer = RunLogWriter;
    fn make_writer(&'a self) -> Self::Writer {
        RunLogWriter
    }
}

/// Installs the subscriber: stderr at warn (`verbose` 1: info, 2 or more: debug), the run
/// log at info. Call once.
pub fn init(verbose: u8) {
    let stderr_level = match verbose {
        0 => LevelFilter::WARN,
        1 => LevelFilter::INFO,
        _ => LevelFilter::DEBUG,
    };
    let stderr = tracing_subscriber::fmt::layer()
        .with_writer(std::io::stderr)
        .with_target(false)
        .with_filter(stderr_level);
    let file = tracing_subscriber::fmt::layer()
        .with_writer(RunLogWriter)
        .with_ansi(false)
        .with_filter(LevelFilter::INFO);
    let _ = tracing_subscriber::registry()
        .with(stderr)
        .with(file)
        .try_init();
}

/// The run log stays open until this is dropped.
#[derive(Debug)]
pub struct RunLog(());

impl Drop for RunLog {
    fn drop(&mut self) {
        if let Ok(mut g) = RUN_LOG.lock() {
            if let Some(mut f) = g.take() {
                let _ = f.flush();
            }
        }
    }
}

/// Opens (appends to) `run_dir/run.log` as the run's log; `None` if it cannot (the run goes
/// on without a log file, with a warning).
pub fn to_run_dir(run_dir: &Path) -> Option<RunLog> {
    if let Err(e) = std::fs::create_dir_all(run_dir) {
        tracing::warn!("no run log: {}: {e}", run_dir.display());
        return None;
    }
    let path = run_dir.join("run.log");
    match std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&path)
    {
        Ok(f) => {
            if let Ok(mut g) = RUN_LOG.lock() {
                *g = Some(f);
            }
            Some(RunLog(()))
        }
        Err(e) => {
            tracing::warn!("no run log: {}: {e}", path.display());
            None
        }
    }
}
