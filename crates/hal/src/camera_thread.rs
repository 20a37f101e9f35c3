//! A blocking camera SDK on its own named thread, as an async [`Camera`]
//! (`ARCHITECTURE.md`, "Device abstraction": blocking SDKs run on a named thread and feed a
//! bounded channel).
//!
//! The thread owns the [`BlockingCamera`]. It runs the caller's settings in order. While
//! streaming, it waits on the SDK in short slices, so a setting never waits longer than one
//! slice. Complete frames go into a bounded queue. When the queue is full, the **oldest** frame
//! is dropped and counted: the thread never waits for the consumer, and after a move the freshest
//! frame is the one wanted. Incomplete buffers are counted and never handed out. A
//! [`ErrorKind::Disconnected`] from the SDK ends the stream, and every later grab reports it.

use crate::{
    BlockingCamera, Camera, CameraInfo, DeviceError, ErrorKind, Frame, Grabbed, PixelFormat, Roi,
    StreamStats, TriggerMode,
};
use std::collections::VecDeque;
use std::sync::mpsc as std_mpsc;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;
use tokio::sync::{oneshot, watch, Notify};

/// How the thread and the queue behave.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThreadPolicy {
    /// Frames held for the consumer; beyond it the oldest is dropped. At least 1.
    pub queue_frames: usize,
    /// The longest one wait on the SDK while streaming (also the worst extra latency of a
    /// setting made while streaming).
    pub poll: Duration,
    /// Deadline of one setting (exposure, gain, start, ...).
    pub command_timeout: Duration,
}

impl Default for ThreadPolicy {
    fn default() -> Self {
        ThreadPolicy {
            queue_frames: 4,
            poll: Duration::from_millis(20),
            command_timeout: Duration::from_secs(5),
        }
    }
}

type Reply<T> = oneshot::Sender<Result<T, DeviceError>>;

enum Command {
    Exposure(f64, Reply<f64>),
    Gain(f64, Reply<f64>),
    Format(PixelFormat, Reply<()>),
    Region(Roi, Reply<Roi>),
    Trigger(TriggerMode, Reply<()>),
    Start(Reply<()>),
    Stop(Reply<()>),
    Fire(Reply<()>),
}

#[derive(Default)]
struct State {
    queue: VecDeque<Frame>,
    stats: StreamStats,
    /// Set when the stream ended for good (disconnect, the thread gone).
    ended: Option<DeviceError>,
}

struct Shared {
    state: Mutex<State>,
    ready: Notify,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        // A panic while holding the lock leaves plain counters and frames behind: still usable.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// An async [`Camera`] over a [`BlockingCamera`] run on a named thread.
pub struct ThreadedCamera {
    info: CameraInfo,
    hardware_trigger: bool,
    software_trigger: bool,
    policy: ThreadPolicy,
    commands: std_mpsc::Sender<Command>,
    shared: Arc<Shared>,
    /// Exposure ends reported by the camera: (how many so far, the last one's frame id); `None`
    /// when the camera does not report them.
    exposures: Option<watch::Receiver<(u64, u64)>>,
    /// The exposure-end count when the last trigger was fired.
    armed: u64,
}

impl ThreadedCamera {
    /// Moves `camera` onto a new thread named `camera-<id>`. Fails only if the thread cannot be
    /// spawned.
    pub fn spawn<C: BlockingCamera>(
        mut camera: C,
        policy: ThreadPolicy,
    ) -> Result<ThreadedCamera, DeviceError> {
        let info = camera.info();
        let (ended, exposures) = watch::channel((0u64, 0u64));
        let reports_exposure_end = camera.on_exposure_end(Box::new(move |frame_id| {
            ended.send_modify(|(count, id)| {
                *count += 1;
                *id = frame_id;
            });
        }));
        let hardware_trigger = camera.supports_hardware_trigger();
        let software_trigger = camera.supports_software_trigger();
        let policy = ThreadPolicy {
            queue_frames: policy.queue_frames.max(1),
            ..policy
        };
        let shared = Arc::new(Shared {
            state: Mutex::new(State::default()),
            ready: Notify::new(),
        });
        let (tx, rx) = std_mpsc::channel();
        let thread_shared = Arc::clone(&shared);
        std::thread::Builder::new()
            .name(format!("camera-{}", info.id))
            .spawn(move || run(camera, rx, &thread_shared, policy))
            .map_err(|e| {
                DeviceError::new(
                    ErrorKind::Other,
                    &info.id,
                    format!("cannot start the camera thread: {e}"),
                )
            })?;
        Ok(ThreadedCamera {
            info,
            hardware_trigger,
            software_trigger,
            policy,
            commands: tx,
            shared,
            exposures: reports_exposure_end.then_some(exposures),
            armed: 0,
        })
    }

    /// Frames waiting in the queue.
    pub fn pending(&self) -> usize {
        self.shared.lock().queue.len()
    }

    /// Drops the frames waiting in the queue (for example those exposed during a move) and
    /// returns how many (they are not counted as dropped).
    pub fn discard_pending(&self) -> usize {
        let mut state = self.shared.lock();
        let n = state.queue.len();
        state.queue.clear();
        n
    }

    fn gone(&self) -> DeviceError {
        self.shared.lock().ended.clone().unwrap_or_else(|| {
            DeviceError::new(
                ErrorKind::Disconnected,
                &self.info.id,
                "the camera thread has ended",
            )
        })
    }

    async fn call<T>(&self, make: impl FnOnce(Reply<T>) -> Command) -> Result<T, DeviceError> {
        let (tx, rx) = oneshot::channel();
        self.commands.send(make(tx)).map_err(|_| self.gone())?;
        match tokio::time::timeout(self.policy.command_timeout, rx).await {
            Ok(Ok(reply)) => reply,
            Ok(Err(_)) => Err(self.gone()),
            Err(_) => Err(DeviceError::new(
                ErrorKind::Timeout,
                &self.info.id,
                format!(
                    "no answer from the camera thread within {:?}",
                    self.policy.command_timeout
                ),
            )),
        }
    }
}

impl Camera for ThreadedCamera {
    fn info(&self) -> &CameraInfo {
        &self.info
    }

    async fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, DeviceError> {
        self.info.check_exposure_us(exposure_us)?;
        self.call(|r| Command::Exposure(exposure_us, r)).await
    }

    async fn set_gain(&mut self, gain: f64) -> Result<f64, DeviceError> {
        self.info.check_gain(gain)?;
        self.call(|r| Command::Gain(gain, r)).await
    }

    async fn set_pixel_format(&mut self, format: PixelFormat) -> Result<(), DeviceError> {
        self.info.check_format(format)?;
        self.call(|r| Command::Format(format, r)).await
    }

    async fn set_roi(&mut self, roi: Roi) -> Result<Roi, DeviceError> {
        roi.check(
            &self.info.id,
            self.info.sensor_width,
            self.info.sensor_height,
        )?;
        self.call(|r| Command::Region(roi, r)).await
    }

    async fn set_trigger(&mut self, mode: TriggerMode) -> Result<(), DeviceError> {
        if mode == TriggerMode::Hardware && !self.hardware_trigger {
            return Err(DeviceError::new(
                ErrorKind::OutOfRange,
                &self.info.id,
                "trigger = hardware is not offered by this camera: allowed free-run, software",
            ));
        }
        if mode == TriggerMode::Software && !self.software_trigger {
            return Err(DeviceError::new(
                ErrorKind::OutOfRange,
                &self.info.id,
                "trigger = software is not offered by this camera: allowed free-run",
            ));
        }
        self.call(|r| Command::Trigger(mode, r)).await
    }

    fn supports_hardware_trigger(&self) -> bool {
        self.hardware_trigger
    }

    fn supports_software_trigger(&self) -> bool {
        self.software_trigger
    }

    async fn start(&mut self) -> Result<(), DeviceError> {
        self.call(Command::Start).await
    }

    async fn stop(&mut self) -> Result<(), DeviceError> {
        let r = self.call(Command::Stop).await;
        self.discard_pending();
        r
    }

    async fn trigger(&mut self) -> Result<(), DeviceError> {
        if let Some(rx) = &self.exposures {
            self.armed = rx.borrow().0;
        }
        self.call(Command::Fire).await
    }

    async fn exposure_end(&mut self, deadline: Duration) -> Result<Option<u64>, DeviceError> {
        let armed = self.armed;
        let Some(rx) = &mut self.exposures else {
            return Ok(None);
        };
        let waited = tokio::time::timeout(deadline, rx.wait_for(|&(count, _)| count > armed))
            .await
            .map(|r| r.map(|ended| ended.1));
        match waited {
            Ok(Ok(frame_id)) => Ok(Some(frame_id)),
            // The hook went with the camera thread.
            Ok(Err(_)) => Err(self.gone()),
            Err(_) => Err(DeviceError::new(
                ErrorKind::Timeout,
                &self.info.id,
                format!("no exposure end within {deadline:?} of the trigger"),
            )),
        }
    }

    async fn grab(&mut self, deadline: Duration) -> Result<Frame, DeviceError> {
        let until = tokio::time::Instant::now() + deadline;
        loop {
            {
                let mut state = self.shared.lock();
                if let Some(frame) = state.queue.pop_front() {
                    state.stats.delivered += 1;
                    return Ok(frame);
                }
                if let Some(e) = &state.ended {
                    return Err(e.clone());
                }
                if deadline.is_zero() {
                    // A poll of the queue: tokio's timer would only fire at its next
                    // millisecond tick.
                    return Err(DeviceError::new(
                        ErrorKind::Timeout,
                        &self.info.id,
                        "no complete frame waiting",
                    ));
                }
            }
            // `notify_one` leaves a permit when nobody waits, so a frame queued between the
            // check above and this wait is not missed.
            if tokio::time::timeout_at(until, self.shared.ready.notified())
                .await
                .is_err()
            {
                self.shared.lock().stats.timeouts += 1;
                return Err(DeviceError::new(
                    ErrorKind::Timeout,
                    &self.info.id,
                    format!("no complete frame within {deadline:?}"),
                ));
            }
        }
    }

    fn stats(&self) -> StreamStats {
        self.shared.lock().stats
    }
}

fn answer<T>(reply: Reply<T>, result: Result<T, DeviceError>) {
    // The caller may have given up (its deadline passed); nothing to do then.
    let _ = reply.send(result);
}

/// The camera thread: settings in order, frames into the queue.
fn run<C: BlockingCamera>(
    mut camera: C,
    commands: std_mpsc::Receiver<Command>,
    shared: &Shared,
    policy: ThreadPolicy,
) {
    let id = camera.info().id;
    let mut streaming = false;
    // In software-trigger mode with no trigger outstanding, no frame can come: the thread
    // waits on the commands instead of the SDK, so a trigger starts its exposure at once
    // rather than after the SDK's poll.
    let mut software = false;
    let mut awaiting = false;
    loop {
        let idle = streaming && software && !awaiting;
        let next = if idle {
            match commands.recv_timeout(policy.poll) {
                Ok(c) => Some(c),
                Err(std_mpsc::RecvTimeoutError::Timeout) => continue,
                Err(std_mpsc::RecvTimeoutError::Disconnected) => break,
            }
        } else if streaming {
            match commands.try_recv() {
                Ok(c) => Some(c),
                Err(std_mpsc::TryRecvError::Empty) => None,
                Err(std_mpsc::TryRecvError::Disconnected) => break,
            }
        } else {
            match commands.recv() {
                Ok(c) => Some(c),
                Err(_) => break,
            }
        };
        if let Some(command) = next {
            match command {
                Command::Exposure(v, r) => answer(r, camera.set_exposure_us(v)),
                Command::Gain(v, r) => answer(r, camera.set_gain(v)),
                Command::Format(f, r) => answer(r, camera.set_pixel_format(f)),
                Command::Region(roi, r) => answer(r, camera.set_roi(roi)),
                Command::Trigger(m, r) => {
                    let result = camera.set_trigger(m);
                    if result.is_ok() {
                        software = m == TriggerMode::Software;
                    }
                    answer(r, result)
                }
                Command::Fire(r) => {
                    let result = camera.trigger();
                    if result.is_ok() {
                        awaiting = true;
                    }
                    answer(r, result)
                }
                Command::Start(r) => {
                    let result = camera.start();
                    if result.is_ok() {
                        shared.lock().ended = None;
                        streaming = true;
                    }
                    answer(r, result);
                }
                Command::Stop(r) => {
                    streaming = false;
                    awaiting = false;
                    answer(r, camera.stop());
                }
            }
            continue;
        }
        let waited = camera.wait_frame(policy.poll);
        // The transport's counters change only with a buffer: read them then, not every poll.
        if matches!(waited, Ok(Grabbed::Frame(_) | Grabbed::Incomplete { .. })) {
            if let Some(t) = camera.transport_stats() {
                shared.lock().stats.transport = Some(t);
            }
        }
        match waited {
            Ok(Grabbed::Frame(frame)) => {
                awaiting = false;
                let mut state = shared.lock();
                if state.queue.len() >= policy.queue_frames {
                    state.queue.pop_front();
                    state.stats.dropped += 1;
                }
                state.queue.push_back(frame);
                drop(state);
                shared.ready.notify_one();
            }
            Ok(Grabbed::Incomplete { frame_id, reason }) => {
                awaiting = false;
                shared.lock().stats.incomplete += 1;
                tracing::debug!(camera = %id, ?frame_id, %reason, "incomplete buffer");
            }
            Ok(Grabbed::Nothing) => {}
            Err(e) if e.kind() == ErrorKind::Disconnected => {
                tracing::warn!(camera = %id, error = %e, "camera disconnected");
                streaming = false;
                shared.lock().ended = Some(e);
                shared.ready.notify_one();
            }
            Err(e) => {
                // A transient SDK error: count it as an incomplete buffer and go on.
                shared.lock().stats.incomplete += 1;
                tracing::debug!(camera = %id, error = %e, "stream error");
            }
        }
    }
    let mut state = shared.lock();
    if state.ended.is_none() {
        state.ended = Some(DeviceError::new(
            ErrorKind::Disconnected,
            &id,
            "the camera was closed",
        ));
    }
    drop(state);
    shared.ready.notify_one();
    let _ = camera.stop();
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::GainUnit;
    use std::sync::atomic::{AtomicU64, Ordering};
    use std::time::{Instant, SystemTime};

    /// A scripted blocking camera: one frame every `period`, frame ids counting up; every
    /// `incomplete_every`-th buffer incomplete; disconnects after `disconnect_after` buffers.
    struct Scripted {
        period: Duration,
        next_id: u64,
        incomplete_every: u64,
        disconnect_after: u64,
        exposure_us: f64,
        started: bool,
        produced: Arc<AtomicU64>,
    }

    impl BlockingCamera for Scripted {
        fn info(&self) -> CameraInfo {
            CameraInfo {
                id: "scripted".into(),
                vendor: "test".into(),
                model: "scripted".into(),
                serial: String::new(),
                sensor_width: 4,
                sensor_height: 2,
                exposure_range_us: [10.0, 1e6],
                gain_range: [0.0, 10.0],
                gain_unit: GainUnit::Raw,
                formats: vec![PixelFormat::Mono8],
            }
        }
        fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, DeviceError> {
            // The device rounds to whole 10 us steps, as real ones round to their increments.
            self.exposure_us = (exposure_us / 10.0).round() * 10.0;
            Ok(self.exposure_us)
        }
        fn set_gain(&mut self, gain: f64) -> Result<f64, DeviceError> {
            Ok(gain.round())
        }
        fn set_pixel_format(&mut self, _format: PixelFormat) -> Result<(), DeviceError> {
            Ok(())
        }
        fn set_roi(&mut self, roi: Roi) -> Result<Roi, DeviceError> {
            Ok(roi)
        }
        fn set_trigger(&mut self, _mode: TriggerMode) -> Result<(), DeviceError> {
            Ok(())
        }
        fn start(&mut self) -> Result<(), DeviceError> {
            self.started = true;
            Ok(())
        }
        fn stop(&mut self) -> Result<(), DeviceError> {
            self.started = false;
            Ok(())
        }
        fn trigger(&mut self) -> Result<(), DeviceError> {
            Ok(())
        }
        fn wait_frame(&mut self, wait: Duration) -> Result<Grabbed, DeviceError> {
            if !self.started {
                std::thread::sleep(wait);
                return Ok(Grabbed::Nothing);
            }
            std::thread::sleep(self.period.min(wait));
            let id = self.next_id;
            self.next_id += 1;
            self.produced.fetch_add(1, Ordering::SeqCst);
            if id >= self.disconnect_after {
                return Err(DeviceError::new(
                    ErrorKind::Disconnected,
                    "scripted",
                    "unplugged",
                ));
            }
            if self.incomplete_every > 0 && id % self.incomplete_every == self.incomplete_every - 1
            {
                return Ok(Grabbed::Incomplete {
                    frame_id: Some(id),
                    reason: "missing packets".into(),
                });
            }
            Ok(Grabbed::Frame(Frame {
                pixels: vec![id as u16 % 256; 8],
                width: 4,
                height: 2,
                format: PixelFormat::Mono8,
                host_time: SystemTime::now(),
                device_timestamp_ns: Some(id * 1000),
                frame_id: id,
                exposure_us: self.exposure_us,
                gain: 0.0,
            }))
        }
    }

    fn scripted(incomplete_every: u64, disconnect_after: u64) -> (Scripted, Arc<AtomicU64>) {
        let produced = Arc::new(AtomicU64::new(0));
        (
            Scripted {
                period: Duration::from_millis(2),
                next_id: 0,
                incomplete_every,
                disconnect_after,
                exposure_us: 1000.0,
                started: false,
                produced: Arc::clone(&produced),
            },
            produced,
        )
    }

    /// A camera that does not report exposure ends says so (`None`, at once, so a caller falls
    /// back to waiting for the frame), and a zero-deadline grab is a poll of the queue: a
    /// timeout without a frame, not counted as a stream timeout.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn no_exposure_end_report_and_zero_deadline_poll() {
        let (cam, _) = scripted(0, u64::MAX);
        let mut cam = ThreadedCamera::spawn(cam, ThreadPolicy::default()).expect("spawn");
        assert_eq!(
            cam.exposure_end(Duration::from_secs(5)).await.expect("end"),
            None
        );
        let e = cam.grab(Duration::ZERO).await.expect_err("nothing queued");
        assert_eq!(e.kind(), ErrorKind::Timeout, "{e}");
        assert_eq!(cam.stats().timeouts, 0);
        cam.start().await.expect("start");
        let f = cam.grab(Duration::from_secs(5)).await.expect("frame");
        assert_eq!(f.frame_id, 0);
    }

    /// A consumer that stops grabbing does not stop the camera thread: it keeps producing,
    /// the queue holds at most `queue_frames`, the rest are counted as dropped, and the frames
    /// then grabbed are the newest ones, in order. Settings answer with the applied value.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn slow_consumer_drops_oldest_and_counts() {
        let (cam, produced) = scripted(0, u64::MAX);
        let policy = ThreadPolicy {
            queue_frames: 3,
            ..ThreadPolicy::default()
        };
        let mut cam = ThreadedCamera::spawn(cam, policy).expect("spawn");
        assert_eq!(cam.set_exposure_us(1234.0).await.expect("exposure"), 1230.0);
        cam.start().await.expect("start");
        // Stop consuming while the thread produces at least 20 frames.
        let t0 = Instant::now();
        while produced.load(Ordering::SeqCst) < 20 {
            assert!(
                t0.elapsed() < Duration::from_secs(10),
                "the camera thread stalled"
            );
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        let a = cam.grab(Duration::from_secs(1)).await.expect("frame");
        let b = cam.grab(Duration::from_secs(1)).await.expect("frame");
        assert!(b.frame_id > a.frame_id);
        assert!(a.frame_id >= 15, "old frames were kept: {}", a.frame_id);
        assert_eq!(a.exposure_us, 1230.0);
        cam.stop().await.expect("stop");
        let s = cam.stats();
        assert!(s.dropped >= 15, "{s:?}");
        assert_eq!(s.delivered, 2);
        // Every frame produced is accounted for: delivered, dropped, or discarded at stop.
        assert!(s.delivered + s.dropped <= produced.load(Ordering::SeqCst));
    }

    /// Incomplete buffers are counted and never delivered; a disconnect ends the stream with
    /// `Disconnected` on the next grab after the queued frames, well within the grab deadline.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn incomplete_counted_and_disconnect_reported() {
        let (cam, _) = scripted(3, 12);
        let mut cam = ThreadedCamera::spawn(cam, ThreadPolicy::default()).expect("spawn");
        cam.start().await.expect("start");
        let mut ids = Vec::new();
        let err = loop {
            match cam.grab(Duration::from_secs(5)).await {
                Ok(f) => ids.push(f.frame_id),
                Err(e) => break e,
            }
        };
        assert_eq!(err.kind(), ErrorKind::Disconnected, "{err}");
        assert!(
            ids.iter().all(|id| id % 3 != 2),
            "an incomplete frame was delivered: {ids:?}"
        );
        assert_eq!(cam.stats().incomplete, 4, "ids 2, 5, 8, 11 are incomplete");
        // Later calls keep saying so, at once.
        let t0 = Instant::now();
        let again = cam.grab(Duration::from_secs(5)).await.expect_err("ended");
        assert_eq!(again.kind(), ErrorKind::Disconnected);
        assert!(t0.elapsed() < Duration::from_secs(1));
    }

    /// A grab with nothing streaming times out at its deadline and is counted; bad settings
    /// are refused before they reach the thread, naming the value and the range.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn deadline_and_range_checks() {
        let (cam, _) = scripted(0, u64::MAX);
        let mut cam = ThreadedCamera::spawn(cam, ThreadPolicy::default()).expect("spawn");
        let t0 = Instant::now();
        let e = cam
            .grab(Duration::from_millis(100))
            .await
            .expect_err("nothing");
        assert_eq!(e.kind(), ErrorKind::Timeout);
        assert!(t0.elapsed() >= Duration::from_millis(100));
        assert_eq!(cam.stats().timeouts, 1);
        let e = cam.set_exposure_us(5.0).await.expect_err("too short");
        assert!(
            e.message
                .contains("exposure_us = 5 is out of range: allowed [10, 1000000]"),
            "{e}"
        );
        let e = cam
            .set_trigger(TriggerMode::Hardware)
            .await
            .expect_err("no hw trigger");
        assert_eq!(e.kind(), ErrorKind::OutOfRange);
        let e = cam
            .set_pixel_format(PixelFormat::Mono16)
            .await
            .expect_err("not offered");
        assert!(e.message.contains("allowed Mono8"), "{e}");
    }
}
