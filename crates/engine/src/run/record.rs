//! A frame's record in the journal and the store: the plan step it takes, the camera's
//! metadata, where the analyzer was during the exposure (a settled angle or a span), and the
//! sun's position at the frame's time when the plan names a site.

use super::clock::now_unix_ns;
use crate::plan::StepSpec;
use crate::{pixel_hash, FrameRecord};
use polar_hal::Frame;

/// Where the analyzer was during a frame's exposure (the store's span columns).
pub(super) struct FrameSpan {
    /// The span's start, degrees in `[0, 180)` (the settled angle for step-and-shoot).
    pub(super) start_deg: f64,
    /// Its end, degrees (equal to the start for step-and-shoot).
    pub(super) end_deg: f64,
    /// How it was measured.
    pub(super) source: crate::AngleSource,
    /// Its standard uncertainty, degrees (NaN where not estimated).
    pub(super) sigma_deg: f64,
}

impl FrameSpan {
    /// A still analyzer at its measured angle.
    pub(super) fn settled(measured_deg: f64) -> FrameSpan {
        FrameSpan {
            start_deg: measured_deg,
            end_deg: measured_deg,
            source: crate::AngleSource::Settled,
            sigma_deg: f64::NAN,
        }
    }
}

/// The record of `frame`, stored as frame `index` for plan step `step` (`spec`), with its
/// analyzer span; the sun's zenith and azimuth are the rig's fixed `sun_deg` (a simulated
/// sun) or else computed for the frame's host time at `site`.
pub(super) fn frame_record(
    (index, step, spec): (u64, u64, &StepSpec),
    frame: &Frame,
    span: FrameSpan,
    sun_deg: Option<(f64, f64)>,
    site: Option<&crate::plan::Site>,
) -> FrameRecord {
    let host_ns = now_unix_ns(frame.host_time);
    let (zen, az) = sun_deg
        .or_else(|| site.and_then(|s| sun_at(host_ns, s)))
        .map_or((None, None), |(z, a)| (Some(z), Some(a)));
    FrameRecord {
        index,
        step,
        kind: spec.kind,
        set: spec.set,
        label: spec.label.clone(),
        commanded_angle_deg: spec.angle_deg.rem_euclid(180.0),
        measured_angle_deg: span.start_deg,
        angle_start_deg: span.start_deg,
        angle_end_deg: span.end_deg,
        angle_source: span.source,
        angle_sigma_deg: span.sigma_deg,
        exposure_us: frame.exposure_us,
        gain: frame.gain,
        host_time_unix_ns: host_ns,
        device_timestamp_ns: frame.device_timestamp_ns,
        frame_id: frame.frame_id,
        sun_zenith_deg: zen,
        sun_azimuth_deg: az,
        width: frame.width,
        height: frame.height,
        hash: pixel_hash(&frame.pixels),
    }
}

/// The sun's zenith and azimuth at a Unix time (ns) for a site (NREL SPA, geometric).
pub(super) fn sun_at(unix_ns: i64, site: &crate::plan::Site) -> Option<(f64, f64)> {
    use chrono::{Datelike, Timelike};
    let t = chrono::DateTime::from_timestamp(
        unix_ns.div_euclid(1_000_000_000),
        u32::try_from(unix_ns.rem_euclid(1_000_000_000)).ok()?,
    )?;
    let time = polar_model::sun::UtcTime {
        year: t.year(),
        month: t.month(),
        day: t.day(),
        hour: t.hour(),
        minute: t.minute(),
        second: f64::from(t.second()) + f64::from(t.nanosecond()) * 1e-9,
    };
    let s = polar_model::sun::Site::new(site.latitude_deg, site.longitude_deg, site.elevation_m)
        .ok()?;
    let p = polar_model::sun::sun_position(&time, &s, None, None).ok()?;
    Some((p.zenith_deg, p.azimuth_deg))
}
