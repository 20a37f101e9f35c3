//! When an item may run: a window given by the sun's elevation at the rig's site (above or
//! below a value, only while rising or only while setting; the model's NREL SPA, geometric,
//! as the run records it), by local time (a fixed UTC offset), and not before an instant; and
//! an interval with repeats. `{"sun_above_deg": 10, "every_s": 600}` is a daily time-lapse
//! from 10 deg rising to 10 deg setting, every 10 minutes.

use chrono::{DateTime, Datelike, Timelike};
use serde::{Deserialize, Serialize};

/// How far ahead [`Schedule::next_start`] looks, seconds.
pub const HORIZON_S: u64 = 3 * 86_400;
/// The step of that search, seconds (a window opening is found to within it).
pub const STEP_S: u64 = 60;

/// The site the sun is computed for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SunSite {
    /// Degrees north.
    pub latitude_deg: f64,
    /// Degrees east.
    pub longitude_deg: f64,
    /// Metres above sea level.
    pub elevation_m: f64,
}

/// Which half of the day a sun window keeps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SunPhase {
    /// The sun is climbing (morning).
    Rising,
    /// The sun is sinking (afternoon).
    Setting,
}

/// An item's schedule (module docs); every condition given must hold.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Schedule {
    /// Not before this instant (RFC 3339).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub not_before: Option<String>,
    /// Only while the sun is above this elevation, degrees.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sun_above_deg: Option<f64>,
    /// Only while the sun is below this elevation, degrees.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sun_below_deg: Option<f64>,
    /// Only while the sun rises, or only while it sets.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sun_phase: Option<SunPhase>,
    /// Local time of day from which it may start, `HH:MM` (the station's `utc_offset_h`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub local_from: Option<String>,
    /// Local time of day until which it may start, `HH:MM` (before `local_from`: past midnight).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub local_to: Option<String>,
    /// Start again this long after each start, seconds (1 to 30 days).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub every_s: Option<u64>,
    /// Runs in all (default: 1 without `every_s`, no limit with it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub repeats: Option<u32>,
}

/// Seconds since midnight of `HH:MM`.
fn parse_hhmm(text: &str) -> Option<u64> {
    let (h, m) = text.split_once(':')?;
    let (h, m): (u64, u64) = (h.parse().ok()?, m.parse().ok()?);
    (h < 24 && m < 60).then_some(h * 3600 + m * 60)
}

/// The sun's elevation (90 deg less the geometric zenith) at `unix_s`, degrees.
pub fn sun_elevation_deg(site: &SunSite, unix_s: u64) -> Option<f64> {
    let t = DateTime::from_timestamp(i64::try_from(unix_s).ok()?, 0)?;
    let time = polar_model::sun::UtcTime {
        year: t.year(),
        month: t.month(),
        day: t.day(),
        hour: t.hour(),
        minute: t.minute(),
        second: f64::from(t.second()),
    };
    let s = polar_model::sun::Site::new(site.latitude_deg, site.longitude_deg, site.elevation_m)
        .ok()?;
    let p = polar_model::sun::sun_position(&time, &s, None, None).ok()?;
    Some(90.0 - p.zenith_deg)
}

impl Schedule {
    /// Checks the values; the error names the field (`schedule.FIELD`), the value and the
    /// allowed range. `site` is the rig's (a sun condition needs one).
    pub fn validate(&self, site: Option<&SunSite>) -> Result<(), (String, String)> {
        let bad = |f: &str, m: String| Err((format!("schedule.{f}"), m));
        if let Some(t) = &self.not_before {
            if humantime::parse_rfc3339_weak(t).is_err() {
                return bad(
                    "not_before",
                    format!("{t:?} is not a time: write e.g. 2026-06-21T04:00:00Z"),
                );
            }
        }
        for (f, v) in [
            ("sun_above_deg", self.sun_above_deg),
            ("sun_below_deg", self.sun_below_deg),
        ] {
            if let Some(v) = v {
                if !(-90.0..=90.0).contains(&v) {
                    return bad(
                        f,
                        format!("{v} is out of range: -90 to 90 (degrees of elevation)"),
                    );
                }
                if site.is_none() {
                    return bad(
                        f,
                        "the station's rig file has no [site]: a sun window needs one".into(),
                    );
                }
            }
        }
        if let (Some(a), Some(b)) = (self.sun_above_deg, self.sun_below_deg) {
            if a >= b {
                return bad(
                    "sun_below_deg",
                    format!("{b} is not above sun_above_deg {a}: the window would be empty"),
                );
            }
        }
        if self.sun_phase.is_some() && self.sun_above_deg.is_none() && self.sun_below_deg.is_none()
        {
            return bad("sun_phase", "needs sun_above_deg or sun_below_deg".into());
        }
        for (f, v) in [
            ("local_from", &self.local_from),
            ("local_to", &self.local_to),
        ] {
            if let Some(v) = v {
                if parse_hhmm(v).is_none() {
                    return bad(
                        f,
                        format!("{v:?} is not a time of day: HH:MM, 00:00 to 23:59"),
                    );
                }
            }
        }
        match (&self.local_from, &self.local_to) {
            (Some(_), None) => return bad("local_to", "give local_to with local_from".into()),
            (None, Some(_)) => return bad("local_from", "give local_from with local_to".into()),
            (Some(f), Some(t)) if f == t => {
                return bad(
                    "local_to",
                    format!("{t:?} equals local_from: the window would be empty"),
                )
            }
            _ => {}
        }
        if let Some(e) = self.every_s {
            if !(1..=30 * 86_400).contains(&e) {
                return bad(
                    "every_s",
                    format!("{e} is out of range: 1 to 2592000 (30 days)"),
                );
            }
        }
        if self.repeats == Some(0) {
            return bad("repeats", "0 is out of range: at least 1".into());
        }
        Ok(())
    }

    /// Runs in all (`None`: no limit).
    pub fn total_runs(&self) -> Option<u32> {
        match (self.repeats, self.every_s) {
            (Some(n), _) => Some(n),
            (None, Some(_)) => None,
            (None, None) => Some(1),
        }
    }

    /// Whether runs are left after `runs_done`.
    pub fn runs_left(&self, runs_done: u32) -> bool {
        self.total_runs().is_none_or(|n| runs_done < n)
    }

    /// Whether a run may start at `t`: runs left, the interval since the last start passed,
    /// the window open.
    pub fn ready_at(
        &self,
        t: u64,
        last_start: Option<u64>,
        runs_done: u32,
        site: Option<&SunSite>,
        utc_offset_s: i64,
    ) -> bool {
        self.runs_left(runs_done)
            && last_start.zip(self.every_s).is_none_or(|(l, e)| t >= l + e)
            && self.open_at(t, site, utc_offset_s)
    }

    /// Whether the window is open at `t` (sun, local time, not before).
    pub fn open_at(&self, t: u64, site: Option<&SunSite>, utc_offset_s: i64) -> bool {
        if let Some(nb) = self
            .not_before
            .as_deref()
            .and_then(|s| humantime::parse_rfc3339_weak(s).ok())
        {
            let nb = nb
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs());
            if t < nb {
                return false;
            }
        }
        if let (Some(from), Some(to)) = (
            self.local_from.as_deref().and_then(parse_hhmm),
            self.local_to.as_deref().and_then(parse_hhmm),
        ) {
            let local = (t as i64 + utc_offset_s).rem_euclid(86_400) as u64;
            let inside = if from <= to {
                (from..to).contains(&local)
            } else {
                local >= from || local < to
            };
            if !inside {
                return false;
            }
        }
        if self.sun_above_deg.is_none() && self.sun_below_deg.is_none() {
            return true;
        }
        let Some(site) = site else { return false };
        let Some(e) = sun_elevation_deg(site, t) else {
            return false;
        };
        if self.sun_above_deg.is_some_and(|a| e <= a) || self.sun_below_deg.is_some_and(|b| e >= b)
        {
            return false;
        }
        match self.sun_phase {
            None => true,
            Some(phase) => {
                let later = sun_elevation_deg(site, t + STEP_S).unwrap_or(e);
                (later > e) == (phase == SunPhase::Rising)
            }
        }
    }

    /// The earliest start at or after `now`: the window open, the interval since the last
    /// start passed, runs left; `None` when no run is left or the window does not open
    /// within [`HORIZON_S`].
    pub fn next_start(
        &self,
        now: u64,
        last_start: Option<u64>,
        runs_done: u32,
        site: Option<&SunSite>,
        utc_offset_s: i64,
    ) -> Option<u64> {
        if !self.runs_left(runs_done) {
            return None;
        }
        let not_before = self
            .not_before
            .as_deref()
            .and_then(|s| humantime::parse_rfc3339_weak(s).ok())
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map_or(0, |d| d.as_secs());
        let earliest = match (last_start, self.every_s) {
            (Some(l), Some(e)) => now.max(l + e),
            _ => now,
        }
        .max(not_before);
        let mut t = earliest;
        while t <= earliest + HORIZON_S {
            if self.open_at(t, site, utc_offset_s) {
                return Some(t);
            }
            t += STEP_S;
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const ROCHESTER: SunSite = SunSite {
        latitude_deg: 43.08,
        longitude_deg: -77.67,
        elevation_m: 160.0,
    };
    /// 2026-06-21T00:00:00Z.
    const SOLSTICE: u64 = 1_782_000_000;

    #[test]
    fn a_sun_window_opens_in_the_morning_and_keeps_to_its_half_of_the_day() {
        let s = Schedule {
            sun_above_deg: Some(10.0),
            ..Schedule::default()
        };
        let open = s
            .next_start(SOLSTICE, None, 0, Some(&ROCHESTER), 0)
            .unwrap();
        let e = sun_elevation_deg(&ROCHESTER, open).unwrap();
        assert!(
            (10.0..10.5).contains(&e),
            "opens within a step of 10 deg: {e}"
        );
        let before = sun_elevation_deg(&ROCHESTER, open - STEP_S).unwrap();
        assert!(before <= 10.0, "and not a step earlier: {before}");
        // Rochester is UTC-5 in winter, -4 in summer: 10 deg rising comes near 10:30-11:30 UTC.
        let hour = (open % 86_400) / 3600;
        assert!((9..=12).contains(&hour), "{hour}");
        let setting = Schedule {
            sun_phase: Some(SunPhase::Setting),
            ..s.clone()
        };
        let afternoon = setting
            .next_start(SOLSTICE, None, 0, Some(&ROCHESTER), 0)
            .unwrap();
        assert!(
            afternoon > open + 4 * 3600,
            "the setting half starts after noon"
        );
    }

    #[test]
    fn intervals_repeats_and_local_time() {
        let every = Schedule {
            every_s: Some(600),
            repeats: Some(3),
            ..Schedule::default()
        };
        assert_eq!(every.next_start(1000, Some(900), 1, None, 0), Some(1500));
        assert_eq!(
            every.next_start(1000, Some(900), 3, None, 0),
            None,
            "runs used up"
        );
        let night = Schedule {
            local_from: Some("22:00".into()),
            local_to: Some("02:00".into()),
            ..Schedule::default()
        };
        // 23:00 local at UTC+1 is 22:00 UTC.
        assert!(night.open_at(22 * 3600, None, 3600));
        assert!(!night.open_at(12 * 3600, None, 3600));
        assert_eq!(Schedule::default().total_runs(), Some(1));
        let e = Schedule {
            sun_above_deg: Some(95.0),
            ..Schedule::default()
        }
        .validate(Some(&ROCHESTER))
        .unwrap_err();
        assert_eq!(e.0, "schedule.sun_above_deg");
        let e = Schedule {
            sun_below_deg: Some(-6.0),
            ..Schedule::default()
        }
        .validate(None)
        .unwrap_err();
        assert!(e.1.contains("[site]"), "{e:?}");
    }
}
