//! The thin layer over `linuxvideo` and `poll(2)`: OS errors to [`ErrorKind`]s, and a guard that
//! turns a panic inside the V4L2 library into an error.
//!
//! `linuxvideo` asserts on some device replies (a name without a NUL or not UTF-8, a frame-size
//! type it does not know, a `bytesused` beyond the buffer). A driver must not make this process
//! panic, so every call into it goes through [`guarded`]: a panic there is caught and reported
//! as an [`ErrorKind::Protocol`] error naming the operation. (The default panic hook still
//! prints the panic message to stderr once.)

use crate::convert::panic_message;
use polar_hal::{DeviceError, ErrorKind};
use rustix::event::{PollFd, PollFlags, Timespec};
use rustix::io::Errno;
use std::io;
use std::os::fd::AsFd;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::time::{Duration, Instant};

/// The kind of an OS error from a V4L2 call.
pub(crate) fn kind_of(e: &io::Error) -> ErrorKind {
    match Errno::from_io_error(e) {
        // Unplugged (ENODEV), a transfer or driver failure (EIO, as in nokhwa #47), or the node
        // vanished (ENOENT, ENXIO): the stream is over; reopening may bring it back.
        Some(
            Errno::NODEV | Errno::IO | Errno::NXIO | Errno::NOENT | Errno::SHUTDOWN | Errno::PIPE,
        ) => ErrorKind::Disconnected,
        Some(Errno::BUSY) => ErrorKind::Busy,
        Some(Errno::TIMEDOUT | Errno::AGAIN) => ErrorKind::Timeout,
        Some(Errno::INVAL | Errno::RANGE) => ErrorKind::OutOfRange,
        _ => ErrorKind::Other,
    }
}

/// A [`DeviceError`] for an OS error during `what`, with a hint where one helps.
pub(crate) fn io_error(device: &str, what: &str, e: &io::Error) -> DeviceError {
    let hint = match Errno::from_io_error(e) {
        Some(Errno::ACCESS | Errno::PERM) => {
            " (check the device node's permissions: is the user in the `video` group? \
             For a control, it may be read-only or inactive)"
        }
        Some(Errno::BUSY) => " (another program or handle is using the device)",
        Some(Errno::NOTTY) => " (not a V4L2 device, or the driver lacks this ioctl)",
        _ => "",
    };
    DeviceError::new(kind_of(e), device, format!("{what}: {e}{hint}"))
}

/// Runs `f` (a call into `linuxvideo`), mapping its OS error with [`io_error`] and a panic to
/// an [`ErrorKind::Protocol`] error.
pub(crate) fn guarded<T>(
    device: &str,
    what: &str,
    f: impl FnOnce() -> io::Result<T>,
) -> Result<T, DeviceError> {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(e)) => Err(io_error(device, what, &e)),
        Err(payload) => Err(DeviceError::new(
            ErrorKind::Protocol,
            device,
            format!(
                "{what}: the V4L2 library could not read the device's reply (it panicked: {})",
                panic_message(payload.as_ref())
            ),
        )),
    }
}

/// What one wait on a stream's descriptor saw.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Ready {
    /// A filled buffer can be dequeued without blocking.
    Readable,
    /// The driver reports an error on the queue (`POLLERR`, `POLLHUP` or `POLLNVAL`): it failed
    /// or went away; a dequeue would fail or block.
    Failed,
    /// Nothing within the wait.
    Nothing,
}

/// Waits at most `wait` for the descriptor to become readable (`poll(2)`; interrupted waits are
/// resumed with the time left).
pub(crate) fn wait_readable(fd: &impl AsFd, wait: Duration) -> io::Result<Ready> {
    let deadline = Instant::now() + wait;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        // A duration too large for a timespec waits "for ever", which `wait` never means:
        // cap it at a day.
        let timeout =
            Timespec::try_from(left.min(Duration::from_secs(86_400))).unwrap_or(Timespec {
                tv_sec: 86_400,
                tv_nsec: 0,
            });
        let mut fds = [PollFd::new(fd, PollFlags::IN)];
        match rustix::event::poll(&mut fds, Some(&timeout)) {
            Ok(0) => return Ok(Ready::Nothing),
            Ok(_) => {
                let got = fds[0].revents();
                if got.contains(PollFlags::IN) {
                    return Ok(Ready::Readable);
                }
                if got.intersects(PollFlags::ERR | PollFlags::HUP | PollFlags::NVAL) {
                    return Ok(Ready::Failed);
                }
                if left.is_zero() {
                    return Ok(Ready::Nothing);
                }
            }
            Err(Errno::INTR) => {
                if left.is_zero() {
                    return Ok(Ready::Nothing);
                }
            }
            Err(e) => return Err(e.into()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::net::UnixStream;

    /// The errors the engine acts on map to their kinds: unplug and I/O error end the stream,
    /// EBUSY is busy, a bad value is out of range; permission errors carry a hint.
    #[test]
    fn os_errors_map_to_kinds() {
        let e = |errno: Errno| io::Error::from_raw_os_error(errno.raw_os_error());
        assert_eq!(kind_of(&e(Errno::NODEV)), ErrorKind::Disconnected);
        assert_eq!(kind_of(&e(Errno::IO)), ErrorKind::Disconnected);
        assert_eq!(kind_of(&e(Errno::BUSY)), ErrorKind::Busy);
        assert_eq!(kind_of(&e(Errno::INVAL)), ErrorKind::OutOfRange);
        assert_eq!(kind_of(&e(Errno::NOTTY)), ErrorKind::Other);
        let err = io_error("/dev/video9", "open", &e(Errno::ACCESS));
        assert!(err.message.contains("`video` group"), "{err}");
        assert_eq!(err.device, "/dev/video9");
    }

    /// A panic inside the guarded call becomes a Protocol error naming the operation.
    #[test]
    fn guard_catches_panics() {
        let e = guarded::<()>("/dev/video9", "query caps", || {
            panic!("missing NUL terminator")
        })
        .unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Protocol);
        assert!(e.message.contains("query caps"), "{e}");
        assert!(e.message.contains("missing NUL terminator"), "{e}");
        assert_eq!(guarded("d", "ok", || Ok(3)).unwrap(), 3);
    }

    /// The wait returns Nothing after about its length when nothing arrives (a socket pair
    /// stands in for a stream descriptor), Readable at once when data is there, and Failed
    /// when the peer has gone. Timing tolerance: at least the wait, and under 1 s of slack for
    /// a loaded 2-core machine.
    #[test]
    fn wait_honours_the_deadline() {
        let (a, b) = UnixStream::pair().unwrap();
        let t = Instant::now();
        assert_eq!(
            wait_readable(&a, Duration::from_millis(50)).unwrap(),
            Ready::Nothing
        );
        let took = t.elapsed();
        assert!(
            took >= Duration::from_millis(50) && took < Duration::from_secs(1),
            "{took:?}"
        );
        use std::io::Write;
        (&b).write_all(b"x").unwrap();
        assert_eq!(
            wait_readable(&a, Duration::from_secs(5)).unwrap(),
            Ready::Readable
        );
        let (c, d) = UnixStream::pair().unwrap();
        drop(d);
        // A closed peer reads as end-of-file (POLLIN with POLLHUP): readable or failed, never
        // a wait to the deadline.
        let t = Instant::now();
        let r = wait_readable(&c, Duration::from_secs(5)).unwrap();
        assert_ne!(r, Ready::Nothing);
        assert!(t.elapsed() < Duration::from_secs(1));
    }
}
