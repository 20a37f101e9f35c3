//! The calibrations a plan computes from its frames at the end of the run.

use super::outcome::RunError;
use crate::plan::{Acquisition, Plan};
use crate::store::RunStore;
use crate::{FrameKind, FrameRecord};
use serde_json::Value;
use std::collections::BTreeMap;

/// The calibration a plan computes from its frames: the EMVA 1288 photon transfer
/// (calibrate-noise) or the analyzer's Malus fit (calibrate-analyzer).
pub(super) fn calibrate(
    plan: &Plan,
    reader: &RunStore,
    records: &BTreeMap<u64, FrameRecord>,
    accepted: &BTreeMap<u64, u64>,
) -> Result<Option<(String, Value)>, RunError> {
    let frames_of = |kind: FrameKind| -> Vec<&FrameRecord> {
        accepted
            .values()
            .filter_map(|i| records.get(i))
            .filter(|r| r.kind == kind)
            .collect()
    };
    let bad = |e: String| RunError::Check(format!("calibration: {e}"));
    match &plan.acquisition {
        Acquisition::CalibrateNoise(c) => {
            let mut points = Vec::new();
            for &e in &c.exposure_us {
                let pick = |kind| -> Vec<&FrameRecord> {
                    frames_of(kind)
                        .into_iter()
                        .filter(|r| (r.exposure_us - e).abs() <= 1e-6 * e.max(1.0) + 0.5)
                        .collect()
                };
                let stats = |rs: Vec<&FrameRecord>| -> Result<(f64, f64, usize), RunError> {
                    let (mut m, mut v, mut n, mut pairs) = (0.0, 0.0, 0usize, 0usize);
                    for pair in rs.chunks_exact(2) {
                        let a = reader.read_frame(pair[0].index)?;
                        let b = reader.read_frame(pair[1].index)?;
                        let st = polar_model::calibration::pair_statistics(&a, &b)
                            .map_err(|e| bad(e.to_string()))?;
                        m += st.mean_dn;
                        v += st.temporal_var_dn2;
                        n += st.pixels;
                        pairs += 1;
                    }
                    if pairs == 0 {
                        return Err(bad(format!("no frame pair at {e} us")));
                    }
                    Ok((m / pairs as f64, v / pairs as f64, n))
                };
                let (dm, dv, _) = stats(pick(FrameKind::Dark))?;
                let (fm, fv, n) = stats(pick(FrameKind::Light))?;
                points.push(polar_model::calibration::ExposurePoint {
                    exposure_us: e,
                    photons_per_pixel: None,
                    dark_mean_dn: dm,
                    dark_var_dn2: dv,
                    flat_mean_dn: fm,
                    flat_var_dn2: fv,
                    pixels: n,
                });
            }
            let pt = polar_model::calibration::photon_transfer(&points)
                .map_err(|e| bad(e.to_string()))?;
            Ok(Some((
                "noise".into(),
                serde_json::to_value(&pt).unwrap_or(Value::Null),
            )))
        }
        Acquisition::CalibrateAnalyzer(c) => {
            let mean = |r: &FrameRecord| -> Result<f64, RunError> {
                let px = reader.read_frame(r.index)?;
                Ok(px.iter().map(|&p| f64::from(p)).sum::<f64>() / px.len().max(1) as f64)
            };
            let darks = frames_of(FrameKind::Dark);
            if darks.is_empty() {
                return Err(bad("the extinction ratio needs dark frames".into()));
            }
            let mut dark = 0.0;
            for r in &darks {
                dark += mean(r)?;
            }
            let dark = dark / darks.len() as f64;
            let mut points = Vec::new();
            for r in frames_of(FrameKind::Light) {
                let m = mean(r)?;
                points.push(crate::analyzer_cal::MalusPoint {
                    angle_deg: r.measured_angle_deg,
                    signal: m - dark,
                    variance: None,
                });
            }
            let fit = crate::analyzer_cal::fit_malus(&points, c.reference_angle_deg)
                .map_err(|e| bad(e.to_string()))?;
            Ok(Some((
                "analyzer".into(),
                serde_json::to_value(&fit).unwrap_or(Value::Null),
            )))
        }
        _ => Ok(None),
    }
}
