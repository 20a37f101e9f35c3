//! TIFF export for viewers: every stored frame as a 16-bit grayscale TIFF, every product
//! image as a 32-bit float TIFF, the mean dark frame, and the per-frame metadata as CSV.
//!
//! ```text
//! OUT_DIR/
//!   frame_000000.tif ...        uint16, one per stored frame (by index)
//!   set_0003_dolp.tif ...       float32, one per product image of each processed set
//!                               (set_0003_slot_0002_dolp.tif if a set number repeats)
//!   dark_mean.tif               float32, if the run has darks
//!   frames.csv                  one row per frame record, with a header: its analyzer
//!                               span, whether it counts (accepted, status) and its file
//! ```
//!
//! TIFFs are uncompressed, one image per file, so that any viewer opens them.

use crate::store::{RunStore, StoreError};
use crate::FrameRecord;
use serde::{Deserialize, Serialize};
use std::collections::BTreeSet;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// What [`export_tiff`] wrote.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ExportSummary {
    /// Frame TIFFs written.
    pub frames: u64,
    /// Product TIFFs written.
    pub products: u64,
    /// A dark-mean TIFF was written.
    pub dark_mean: bool,
    /// Rows of `frames.csv`.
    pub csv_rows: u64,
    /// Frames (or product images) that could not be read, with the reason: the export goes
    /// on without them.
    pub skipped: Vec<String>,
}

/// What can go wrong with an export.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// The run's store could not be opened or read.
    #[error("{run_dir}: {source}")]
    Store {
        /// The run directory.
        run_dir: PathBuf,
        /// The store error.
        source: StoreError,
    },
    /// A file could not be written.
    #[error("{path}: {message}")]
    Write {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
}

fn write_err<E: std::fmt::Display>(path: &Path) -> impl FnOnce(E) -> ExportError + '_ {
    move |e| ExportError::Write {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

fn write_tiff_u16(path: &Path, width: u32, height: u32, data: &[u16]) -> Result<(), ExportError> {
    crate::tiff_io::write_gray16(path, width, height, data).map_err(write_err(path))
}

fn write_tiff_f32(path: &Path, width: u32, height: u32, data: &[f32]) -> Result<(), ExportError> {
    crate::tiff_io::write_gray32f(path, width, height, data).map_err(write_err(path))
}

/// The `frames.csv` header.
pub const CSV_HEADER: &str = "index,step,kind,set,label,commanded_angle_deg,measured_angle_deg,\
angle_start_deg,angle_end_deg,angle_source,angle_sigma_deg,accepted,status,\
exposure_us,gain,host_time_unix_ns,device_timestamp_ns,frame_id,sun_zenith_deg,sun_azimuth_deg,\
width,height,hash,file";

fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// The name of `code` in `codes` ("unknown" for a code it does not list).
fn code_name(codes: &[(u8, &str)], code: u8) -> String {
    codes
        .iter()
        .find(|(c, _)| *c == code)
        .map_or("unknown", |(_, n)| n)
        .to_string()
}

fn csv_row(r: &FrameRecord, status: u8, file: &str) -> String {
    let opt_f = |v: Option<f64>| v.map_or(String::new(), |v| v.to_string());
    [
        r.index.to_string(),
        r.step.to_string(),
        match r.kind {
            crate::FrameKind::Light => "light".to_string(),
            crate::FrameKind::Dark => "dark".to_string(),
        },
        r.set.map_or(String::new(), |s| s.to_string()),
        csv_field(&r.label),
        r.commanded_angle_deg.to_string(),
        r.measured_angle_deg.to_string(),
        r.angle_start_deg.to_string(),
        r.angle_end_deg.to_string(),
        code_name(&crate::AngleSource::CODES, r.angle_source.code()),
        r.angle_sigma_deg.to_string(),
        (status == 0).to_string(),
        code_name(&crate::store::STATUS_CODES, status),
        r.exposure_us.to_string(),
        r.gain.to_string(),
        r.host_time_unix_ns.to_string(),
        r.device_timestamp_ns
            .map_or(String::new(), |t| t.to_string()),
        r.frame_id.to_string(),
        opt_f(r.sun_zenith_deg),
        opt_f(r.sun_azimuth_deg),
        r.width.to_string(),
        r.height.to_string(),
        format!("{:016x}", r.hash),
        csv_field(file),
    ]
    .join(",")
}

/// The file name of frame `index`.
pub fn frame_file_name(index: u64) -> String {
    format!("frame_{index:06}.tif")
}

/// Exports the run in `run_dir` to `out_dir` (created if needed): see the module
/// documentation for the files.
pub fn export_tiff(run_dir: &Path, out_dir: &Path) -> Result<ExportSummary, ExportError> {
    let store_err = |source| ExportError::Store {
        run_dir: run_dir.to_path_buf(),
        source,
    };
    let store = RunStore::open(run_dir).map_err(store_err)?;
    std::fs::create_dir_all(out_dir).map_err(write_err(out_dir))?;
    let (w, h) = (store.width(), store.height());
    let mut summary = ExportSummary::default();

    let count = store.frame_count();
    let mut written = BTreeSet::new();
    for index in 0..count {
        match store.read_frame(index) {
            Ok(px) => {
                let path = out_dir.join(frame_file_name(index));
                write_tiff_u16(&path, w, h, &px)?;
                summary.frames += 1;
                written.insert(index);
            }
            Err(e) => summary.skipped.push(format!("frame {index}: {e}")),
        }
    }

    let names = store.product_names().map_err(store_err)?;
    let slots = store.product_slots().map_err(store_err)?;
    let mut sets_seen = BTreeSet::new();
    for slot in &slots {
        let Some(set) = slot.set else { continue };
        let stem = if sets_seen.insert(set) {
            format!("set_{set:04}")
        } else {
            format!("set_{set:04}_slot_{:04}", slot.slot)
        };
        for name in &names {
            match store.read_product(name, slot.slot) {
                Ok(img) => {
                    let path = out_dir.join(format!("{stem}_{name}.tif"));
                    if name == "flags" {
                        // The bit mask: a 16-bit integer image, exact (the values are 0..7).
                        let mask: Vec<u16> = img.iter().map(|&f| f as u16).collect();
                        write_tiff_u16(&path, w, h, &mask)?;
                    } else {
                        write_tiff_f32(&path, w, h, &img)?;
                    }
                    summary.products += 1;
                }
                Err(e) => summary
                    .skipped
                    .push(format!("product {name} of set {set}: {e}")),
            }
        }
    }

    if let Some(mean) = store.read_dark_mean().map_err(store_err)? {
        write_tiff_f32(&out_dir.join("dark_mean.tif"), w, h, &mean)?;
        summary.dark_mean = true;
    }

    let records = store.read_frame_metadata().map_err(store_err)?;
    let status = store.read_frame_status().map_err(store_err)?;
    let csv_path = out_dir.join("frames.csv");
    let file = File::create(&csv_path).map_err(write_err(&csv_path))?;
    let mut csv = BufWriter::new(file);
    writeln!(csv, "{CSV_HEADER}").map_err(write_err(&csv_path))?;
    for r in &records {
        let file = if written.contains(&r.index) {
            frame_file_name(r.index)
        } else {
            String::new()
        };
        let code = status.get(r.index as usize).copied().unwrap_or(0);
        writeln!(csv, "{}", csv_row(r, code, &file)).map_err(write_err(&csv_path))?;
        summary.csv_rows += 1;
    }
    csv.flush().map_err(write_err(&csv_path))?;
    Ok(summary)
}
