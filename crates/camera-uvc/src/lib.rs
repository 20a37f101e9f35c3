//! UVC cameras (webcams and USB video-class machine-vision cameras) on every desktop platform
//! through [`nokhwa`], as a [`polar_hal::BlockingCamera`] (`ARCHITECTURE.md`, "Device
//! abstraction"; `docs/DEVICES.md`, section 3.4).
//!
//! ```no_run
//! use polar_camera_uvc::UvcCamera;
//! use polar_hal::camera_thread::{ThreadPolicy, ThreadedCamera};
//! # fn main() -> Result<(), polar_hal::DeviceError> {
//! for d in polar_camera_uvc::list()? {
//!     println!("{d} -> open with {}", d.spec()); // name, bus info, description
//! }
//! // By bus info or name: never "index 0".
//! let camera = UvcCamera::open("uvc:HD Pro Webcam")?;
//! let camera = ThreadedCamera::spawn(camera, ThreadPolicy::default())?; // an async Camera
//! # Ok(()) }
//! ```
//!
//! # Which crate does what
//!
//! * [`nokhwa`] 0.10 (`input-native`, default features off) drives the platform's camera API:
//!   V4L2 on Linux (through `v4l`, whose bindings bindgen generates at build time, so the Linux
//!   build needs libclang), Media Foundation on Windows, AVFoundation on macOS. Its `decoding`
//!   feature (mozjpeg, C) is left off.
//! * `polar-frame-convert` turns nokhwa's buffers into luminance (the same code the V4L2
//!   backend uses); see [`source`] for the formats.
//! * This crate: enumeration and selection by bus info or name ([`device`]); the per-platform
//!   mapping of manual exposure and gain ([`controls`]); the camera ([`UvcCamera`]) on a thread
//!   of its own with a deadline on every wait.
//!
//! # What is tested where
//!
//! CI has no camera. Its unit tests cover the conversions, device selection, the control
//! mapping of each platform (from synthetic control lists), refusals, and the deadlines of
//! calls and grabs against a camera thread that never answers. `tests/real_device.rs` runs
//! against a real camera when `POLARIMETER_UVC_DEVICE` names one (`uvc:<bus info>` or
//! `uvc:<name>`).
#![warn(missing_docs)]

mod camera;
pub mod controls;
pub mod device;
pub mod source;

pub use camera::{OpenOptions, Source, UvcCamera};
pub use controls::Platform;
pub use device::{list, select, UvcDeviceInfo};
pub use source::SourceFormat;
