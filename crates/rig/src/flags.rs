//! The hardware flags of `polarimeter acquire run`, `acquire resume` and `polarimeter-gui`,
//! defined once: a rig file, flags, or both (a flag overrides the rig file's entry, which
//! overrides the default); without either, the simulated devices. Both programs parse them
//! with clap from this one definition, so they take the same flags with the same checks and
//! the same messages.

use crate::file::{Overrides, Rig};
use crate::hardware::Hardware;
use crate::RigError;
use polar_drivers::registry::DIALECTS;
use std::path::PathBuf;

/// The allowed `--dialect` values, from the dialects' registry, each with its description.
pub fn dialect_values() -> clap::builder::PossibleValuesParser {
    clap::builder::PossibleValuesParser::new(
        DIALECTS
            .iter()
            .map(|d| clap::builder::PossibleValue::new(d.name).help(d.description)),
    )
}

/// Real devices: a rig file, flags, or both.
#[derive(Debug, Default, Clone, clap::Args)]
pub struct HardwareFlags {
    /// The rig file (TOML: [stage] dialect, port, address, model; [camera] backend, id, file;
    /// [site]; [analyzer]). The flags below override its entries.
    #[arg(long)]
    pub rig: Option<PathBuf>,
    /// The stage's serial port (prefer a stable /dev/serial/by-id/... path; `sim`: the
    /// dialect's simulator on a pseudo-terminal).
    #[arg(long)]
    pub port: Option<String>,
    /// The stage's protocol.
    #[arg(long, value_parser = dialect_values())]
    pub dialect: Option<String>,
    /// Bus address (Elliptec 0..=15, SMC100 1..=31); default the rig's, else the dialect's
    /// first.
    #[arg(long, value_parser = clap::value_parser!(u8).range(0..=31))]
    pub address: Option<u8>,
    /// The camera: sim, genicam:ID, v4l:NAME or uvc:BUS_OR_NAME.
    #[arg(long)]
    pub camera: Option<String>,
    /// The camera's noise model (a calibrated camera file, e.g. from `calibrate noise`).
    #[arg(long)]
    pub camera_file: Option<PathBuf>,
    /// Stage angle at which the analyzer's axis is along the camera's x axis, degrees (from a
    /// calibrate-analyzer run); default the rig's, else 0.
    #[arg(long, allow_negative_numbers = true)]
    pub zero_offset_deg: Option<f64>,
}

impl HardwareFlags {
    /// The rig file (if given) and the hardware it and the flags describe (`None`: no device
    /// named, so the simulated devices); `--zero-offset-deg` is checked whether the devices
    /// are real or simulated. Errors name the flag or the rig file's key, the value and what
    /// is allowed.
    pub fn hardware(&self) -> Result<(Option<Hardware>, Option<Rig>), RigError> {
        if let Some(z) = self.zero_offset_deg {
            if !(z.is_finite() && z.abs() <= 360.0) {
                // As typed: 1e300, not its 301 digits.
                let plain = z.to_string();
                let shown = if plain.len() > 16 {
                    format!("{z:e}")
                } else {
                    plain
                };
                return Err(RigError(format!(
                    "--zero-offset-deg = {shown} is out of range: allowed a finite angle in \
                     [-360, 360] degrees"
                )));
            }
        }
        match &self.rig {
            Some(path) => {
                let rig = Rig::load(path).map_err(|e| RigError(format!("--rig: {e}")))?;
                let hw = rig.hardware(&Overrides {
                    port: self.port.clone(),
                    dialect: self.dialect.clone(),
                    address: self.address,
                    camera: self.camera.clone(),
                    camera_file: self.camera_file.clone(),
                    zero_offset_deg: self.zero_offset_deg,
                })?;
                Ok((hw, Some(rig)))
            }
            None => Hardware::from_flags(
                self.port.clone(),
                self.dialect.as_deref(),
                self.camera.clone(),
                self.camera_file.clone(),
                self.address,
                self.zero_offset_deg.unwrap_or(0.0),
            )
            .map(|hw| (hw, None))
            .map_err(RigError),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(flatten)]
        hw: HardwareFlags,
    }

    /// No flag: no hardware (the simulated devices); a dialect outside the registry, an
    /// address past 31 (any bus), an address outside the dialect's bus (Elliptec 0..=15) and a
    /// zero offset past 360 deg are refused naming the flag and what is allowed (clap's
    /// messages for the first two, ours for the others).
    #[test]
    fn flags_are_checked() {
        let none = Cli::try_parse_from(["x"]).unwrap();
        assert!(none.hw.hardware().unwrap().0.is_none());
        let e = Cli::try_parse_from(["x", "--dialect", "smoke"])
            .unwrap_err()
            .to_string();
        assert!(e.contains("--dialect") && e.contains("elliptec"), "{e}");
        let e = Cli::try_parse_from(["x", "--address", "32"])
            .unwrap_err()
            .to_string();
        assert!(e.contains("--address") && e.contains("0..=31"), "{e}");
        let elliptec = Cli::try_parse_from([
            "x",
            "--port",
            "/dev/ttyUSB0",
            "--dialect",
            "elliptec",
            "--address",
            "16",
            "--camera",
            "sim",
            "--camera-file",
            "cam.toml",
        ])
        .unwrap();
        let e = elliptec.hw.hardware().unwrap_err().to_string();
        assert!(e.contains("--address = 16") && e.contains("0..=15"), "{e}");
        let far = Cli::try_parse_from(["x", "--zero-offset-deg", "-400"]).unwrap();
        let e = far.hw.hardware().unwrap_err().to_string();
        assert!(
            e.contains("--zero-offset-deg = -400") && e.contains("[-360, 360]"),
            "{e}"
        );
    }
}
