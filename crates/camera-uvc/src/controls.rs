//! Which nokhwa controls carry manual exposure and gain on each platform, and the conversion of
//! their values to microseconds. Pure: no device is needed to test it.
//!
//! | platform | exposure | gain |
//! |---|---|---|
//! | Linux (V4L2) | `exposure_time_absolute` (`V4L2_CID_EXPOSURE_ABSOLUTE`, reached as `KnownCameraControl::Other`), units of 100 µs; `exposure_auto` is set to manual first | `V4L2_CID_GAIN` (`KnownCameraControl::Gain`), raw |
//! | Windows (Media Foundation) | `CameraControl_Exposure` (`KnownCameraControl::Exposure`), integer log2 seconds; it must already be in manual mode | `VideoProcAmp_Gain` (`KnownCameraControl::Gain`), raw |
//! | macOS (AVFoundation) | none | none |
//!
//! nokhwa's own `KnownCameraControl::Exposure` on Linux is `V4L2_CID_EXPOSURE`, a user-class
//! control in driver units that the UVC driver does not offer; the UVC exposure is the
//! camera-class absolute control above. On Windows nokhwa writes a control with the auto/manual
//! flag it already has, so it cannot take an exposure out of automatic mode. On macOS nokhwa
//! reports the exposure *mode* as `Exposure`, and AVFoundation offers no custom exposure
//! duration or ISO for external cameras, so there is neither manual exposure nor gain.

use nokhwa::utils::{
    ControlValueDescription, ControlValueSetter, KnownCameraControl, KnownCameraControlFlag,
};

/// V4L2 `V4L2_CID_EXPOSURE_AUTO` (camera class): a menu, 1 = manual.
pub const V4L2_CID_EXPOSURE_AUTO: u32 = 0x009a_0901;
/// V4L2 `V4L2_CID_EXPOSURE_ABSOLUTE` (camera class): exposure in units of 100 µs.
pub const V4L2_CID_EXPOSURE_ABSOLUTE: u32 = 0x009a_0902;
/// `V4L2_EXPOSURE_MANUAL`, the manual entry of the `exposure_auto` menu.
pub const V4L2_EXPOSURE_MANUAL: i64 = 1;

/// The platform whose camera API nokhwa drives.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Platform {
    /// Linux, V4L2.
    Linux,
    /// Windows, Media Foundation.
    Windows,
    /// macOS, AVFoundation.
    MacOs,
}

impl Platform {
    /// The platform this build runs on, `None` where nokhwa has no native backend.
    pub fn current() -> Option<Platform> {
        if cfg!(target_os = "linux") {
            Some(Platform::Linux)
        } else if cfg!(target_os = "windows") {
            Some(Platform::Windows)
        } else if cfg!(target_os = "macos") {
            Some(Platform::MacOs)
        } else {
            None
        }
    }

    /// The platform and its camera API, for messages.
    pub fn name(self) -> &'static str {
        match self {
            Platform::Linux => "Linux (V4L2)",
            Platform::Windows => "Windows (Media Foundation)",
            Platform::MacOs => "macOS (AVFoundation)",
        }
    }

    /// The control that carries manual exposure, and its unit; `None` where the platform
    /// offers none.
    pub fn exposure_control(self) -> Option<(KnownCameraControl, ExposureScale)> {
        match self {
            Platform::Linux => Some((
                KnownCameraControl::Other(u128::from(V4L2_CID_EXPOSURE_ABSOLUTE)),
                ExposureScale::HundredMicroseconds,
            )),
            Platform::Windows => Some((KnownCameraControl::Exposure, ExposureScale::Log2Seconds)),
            Platform::MacOs => None,
        }
    }

    /// The control that switches exposure to manual, and the value that does it; `None` where
    /// there is none to write (Windows keeps the mode the control is in).
    pub fn manual_exposure_mode(self) -> Option<(KnownCameraControl, ControlValueSetter)> {
        match self {
            Platform::Linux => Some((
                KnownCameraControl::Other(u128::from(V4L2_CID_EXPOSURE_AUTO)),
                ControlValueSetter::Integer(V4L2_EXPOSURE_MANUAL),
            )),
            Platform::Windows | Platform::MacOs => None,
        }
    }

    /// The control that carries gain (in raw device units); `None` where the platform offers
    /// none.
    pub fn gain_control(self) -> Option<KnownCameraControl> {
        match self {
            Platform::Linux | Platform::Windows => Some(KnownCameraControl::Gain),
            Platform::MacOs => None,
        }
    }
}

/// How an exposure control's integer maps to time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ExposureScale {
    /// Units of 100 µs (V4L2 `exposure_time_absolute`).
    HundredMicroseconds,
    /// `2^value` seconds (DirectShow/Media Foundation `CameraControl_Exposure`).
    Log2Seconds,
}

impl ExposureScale {
    /// The exposure a device value stands for, microseconds.
    pub fn to_us(self, value: i64) -> f64 {
        match self {
            ExposureScale::HundredMicroseconds => value as f64 * 100.0,
            ExposureScale::Log2Seconds => 1e6 * (value as f64).exp2(),
        }
    }

    /// The device value nearest to `exposure_us` (before range and step are applied); for
    /// the log2 scale "nearest" is in ratio, so 1.4 ms goes to 2^-10 s rather than 2^-9 s.
    /// `exposure_us` must be finite and positive.
    pub fn nearest(self, exposure_us: f64) -> i64 {
        match self {
            ExposureScale::HundredMicroseconds => (exposure_us / 100.0).round() as i64,
            ExposureScale::Log2Seconds => (exposure_us * 1e-6).log2().round() as i64,
        }
    }
}

/// An integer control's range and current value, as the device reports it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct IntRange {
    /// Smallest value.
    pub min: i64,
    /// Largest value.
    pub max: i64,
    /// Increment from `min` (1 when the device reports 0).
    pub step: i64,
    /// Current value.
    pub value: i64,
}

impl IntRange {
    /// The range of an integer control's description, `None` for other kinds (menus, booleans,
    /// strings) or for a range with `min > max`.
    pub fn of(description: &ControlValueDescription) -> Option<IntRange> {
        match *description {
            ControlValueDescription::IntegerRange {
                min,
                max,
                value,
                step,
                ..
            } if min <= max => Some(IntRange {
                min,
                max,
                step: step.max(1),
                value,
            }),
            _ => None,
        }
    }

    /// `value` clamped to the range and snapped to the nearest step from `min`.
    pub fn snap(&self, value: i64) -> i64 {
        let clamped = value.clamp(self.min, self.max);
        let steps = ((clamped - self.min) as f64 / self.step as f64).round() as i64;
        let snapped = self.min.saturating_add(steps.saturating_mul(self.step));
        if snapped > self.max {
            snapped - self.step
        } else {
            snapped
        }
    }
}

/// Manual exposure on one opened camera: the control, its unit and its range.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExposureControl {
    /// The nokhwa control written.
    pub control: KnownCameraControl,
    /// Its unit.
    pub scale: ExposureScale,
    /// Its range in device units.
    pub range: IntRange,
}

impl ExposureControl {
    /// The range in microseconds, `[min, max]`.
    pub fn range_us(&self) -> [f64; 2] {
        [
            self.scale.to_us(self.range.min),
            self.scale.to_us(self.range.max),
        ]
    }

    /// The device value for `exposure_us`: the nearest value on the control's grid. Errors (the
    /// message names `exposure_us`, the value and the allowed range in µs) for a value that is not
    /// finite and positive or lies outside the range.
    pub fn device_value(&self, exposure_us: f64) -> Result<i64, String> {
        let [lo, hi] = self.range_us();
        if !(exposure_us.is_finite() && exposure_us > 0.0 && (lo..=hi).contains(&exposure_us)) {
            return Err(format!(
                "exposure_us = {exposure_us} is out of range: allowed [{lo}, {hi}]"
            ));
        }
        Ok(self.range.snap(self.scale.nearest(exposure_us)))
    }
}

/// Manual gain on one opened camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GainControl {
    /// The nokhwa control written.
    pub control: KnownCameraControl,
    /// Its range, raw device units.
    pub range: IntRange,
}

impl GainControl {
    /// The device value for `gain`: the nearest value on the grid. Errors (naming `gain`, the value
    /// and the range) outside the range.
    pub fn device_value(&self, gain: f64) -> Result<i64, String> {
        let (lo, hi) = (self.range.min as f64, self.range.max as f64);
        if !(gain.is_finite() && (lo..=hi).contains(&gain)) {
            return Err(format!(
                "gain = {gain} is out of range: allowed [{lo}, {hi}] (raw device units)"
            ));
        }
        Ok(self.range.snap(gain.round() as i64))
    }
}

/// The message for a control a platform or camera does not offer: names the setting, says the
/// allowed range is empty and why.
pub fn not_offered(setting: &str, value: f64, platform: Option<Platform>, why: &str) -> String {
    let on = platform.map_or("this platform", Platform::name);
    format!("{setting} = {value} is out of range: allowed none, this camera on {on} offers no manual {why}")
}

/// Whether a control reads as being in automatic mode (Windows reports the mode as a flag).
pub fn is_automatic(flags: &[KnownCameraControlFlag]) -> bool {
    flags.contains(&KnownCameraControlFlag::Automatic)
}

/// The integer a control's read-back value holds, if it is one.
pub fn integer_value(value: &ControlValueSetter) -> Option<i64> {
    match *value {
        ControlValueSetter::Integer(v) | ControlValueSetter::EnumValue(v) => Some(v),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn range(min: i64, max: i64, step: i64) -> IntRange {
        IntRange::of(&ControlValueDescription::IntegerRange {
            min,
            max,
            value: min,
            step,
            default: min,
        })
        .expect("an integer range")
    }

    /// V4L2's absolute exposure is in 100 µs units (V4L2 spec, camera control reference):
    /// 10 ms is 100 units, and 100 units read back as exactly 10 000 µs. Values round to the
    /// nearest unit, so the error is at most 50 µs.
    #[test]
    fn linux_exposure_is_hundreds_of_microseconds() {
        let (control, scale) = Platform::Linux.exposure_control().expect("Linux has one");
        assert_eq!(
            control,
            KnownCameraControl::Other(u128::from(V4L2_CID_EXPOSURE_ABSOLUTE))
        );
        let exposure = ExposureControl {
            control,
            scale,
            range: range(3, 2047, 1),
        };
        assert_eq!(exposure.range_us(), [300.0, 204_700.0]);
        assert_eq!(exposure.device_value(10_000.0), Ok(100));
        assert_eq!(scale.to_us(100), 10_000.0);
        assert_eq!(exposure.device_value(10_049.0), Ok(100));
        assert_eq!(exposure.device_value(10_051.0), Ok(101));
        let (mode, value) = Platform::Linux
            .manual_exposure_mode()
            .expect("Linux has one");
        assert_eq!(
            mode,
            KnownCameraControl::Other(u128::from(V4L2_CID_EXPOSURE_AUTO))
        );
        assert_eq!(value, ControlValueSetter::Integer(1));
    }

    /// Windows' exposure is log2 seconds (DirectShow `CameraControl_Exposure`): -5 is 1/32 s =
    /// 31 250 µs exactly; a request snaps to the nearest power of two in ratio (the grid is a
    /// factor of 2 wide, so the applied exposure is within a factor sqrt(2) of the request).
    #[test]
    fn windows_exposure_is_log2_seconds() {
        let (control, scale) = Platform::Windows
            .exposure_control()
            .expect("Windows has one");
        assert_eq!(control, KnownCameraControl::Exposure);
        let exposure = ExposureControl {
            control,
            scale,
            range: range(-13, -1, 1),
        };
        assert_eq!(scale.to_us(-5), 31_250.0);
        assert_eq!(exposure.device_value(31_250.0), Ok(-5));
        // 40 ms: log2(0.04) = -4.64, nearest -5 (31.25 ms, ratio 1.28) not -4 (62.5 ms, 1.56).
        assert_eq!(exposure.device_value(40_000.0), Ok(-5));
        let [lo, hi] = exposure.range_us();
        assert!(
            (lo - 1e6 / 8192.0).abs() < 1e-9 && hi == 500_000.0,
            "{lo} {hi}"
        );
        for v in -13..=-1 {
            let us = scale.to_us(v);
            assert_eq!(exposure.device_value(us), Ok(v), "{us} us");
            if v == -1 {
                break; // 1.4 x 0.5 s is beyond the range
            }
            let applied = scale.to_us(exposure.device_value(us * 1.4).expect("in range"));
            assert!(applied / (us * 1.4) <= 2f64.sqrt() && (us * 1.4) / applied <= 2f64.sqrt());
        }
        assert_eq!(Platform::Windows.manual_exposure_mode(), None);
    }

    /// macOS offers neither manual exposure nor gain through nokhwa; the refusal names the
    /// setting, its value, the empty range and the platform.
    #[test]
    fn macos_offers_no_manual_controls() {
        assert_eq!(Platform::MacOs.exposure_control(), None);
        assert_eq!(Platform::MacOs.gain_control(), None);
        let m = not_offered("exposure_us", 5000.0, Some(Platform::MacOs), "exposure");
        assert_eq!(
            m,
            "exposure_us = 5000 is out of range: allowed none, this camera on macOS (AVFoundation) offers no manual exposure"
        );
        assert_eq!(
            Platform::Linux.gain_control(),
            Some(KnownCameraControl::Gain)
        );
        assert_eq!(
            Platform::Windows.gain_control(),
            Some(KnownCameraControl::Gain)
        );
    }

    /// Out-of-range, zero, negative and non-finite requests are refused with the field, the
    /// value and the range in the message; the range's own ends are accepted.
    #[test]
    fn out_of_range_requests_are_refused() {
        let exposure = ExposureControl {
            control: KnownCameraControl::Exposure,
            scale: ExposureScale::HundredMicroseconds,
            range: range(1, 5000, 1),
        };
        for bad in [50.0, 500_001.0, 0.0, -100.0, f64::NAN, f64::INFINITY] {
            let e = exposure.device_value(bad).unwrap_err();
            assert!(e.starts_with("exposure_us = "), "{e}");
            assert!(e.ends_with("allowed [100, 500000]"), "{e}");
        }
        assert_eq!(exposure.device_value(100.0), Ok(1));
        assert_eq!(exposure.device_value(500_000.0), Ok(5000));
        let gain = GainControl {
            control: KnownCameraControl::Gain,
            range: range(0, 255, 1),
        };
        assert_eq!(gain.device_value(255.0), Ok(255));
        let e = gain.device_value(256.0).unwrap_err();
        assert_eq!(
            e,
            "gain = 256 is out of range: allowed [0, 255] (raw device units)"
        );
        assert!(gain.device_value(f64::NAN).is_err());
    }

    /// Snapping lands on the device's grid (min + k * step), never outside [min, max], and at
    /// most half a step from the clamped request.
    #[test]
    fn snap_stays_on_the_grid() {
        let r = range(3, 250, 4); // grid 3, 7, ..., 247
        for v in -10..300 {
            let s = r.snap(v);
            assert!((r.min..=r.max).contains(&s), "{v} -> {s}");
            assert_eq!((s - r.min) % r.step, 0, "{v} -> {s}");
            let c = v.clamp(r.min, 247);
            assert!((s - c).abs() <= r.step / 2, "{v} -> {s}");
        }
        // A step of 0 from a device is read as 1.
        assert_eq!(range(0, 10, 0).step, 1);
        // Menus and reversed ranges are not integer ranges.
        assert_eq!(
            IntRange::of(&ControlValueDescription::IntegerRange {
                min: 5,
                max: 1,
                value: 3,
                step: 1,
                default: 3
            }),
            None
        );
        assert_eq!(IntRange::of(&ControlValueDescription::None), None);
    }
}
