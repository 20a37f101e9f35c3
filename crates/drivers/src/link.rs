//! The byte link under every dialect: how a port is opened (a serial device path, or anything
//! else that yields a byte stream, such as a simulator's in-memory port), reads and writes
//! with deadlines, input discarded before a request, and the port closed and reopened when
//! the device goes away.
//!
//! Disconnects are what tokio reports for an unplugged tty: end of file on read, or an I/O
//! error (`EIO`, `BrokenPipe`) on read or write (`docs/DEVICES.md` section 5.1).

use polar_hal::{DeviceError, ErrorKind};
use std::future::Future;
use std::io;
use std::pin::Pin;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::time::Instant;

/// A byte stream to a device.
pub trait Io: AsyncRead + AsyncWrite + Unpin + Send {}
impl<T: AsyncRead + AsyncWrite + Unpin + Send> Io for T {}

/// A boxed byte stream.
pub type BoxIo = Box<dyn Io>;

/// The future [`Connector::open`] returns.
pub type OpenFuture<'a> = Pin<Box<dyn Future<Output = io::Result<BoxIo>> + Send + 'a>>;

/// Opens (and reopens) the byte stream to one device.
pub trait Connector: Send + Sync {
    /// The port, as the user names it.
    fn describe(&self) -> String;
    /// Opens the port.
    fn open(&self) -> OpenFuture<'_>;
}

/// A serial port by path, 8N1 without flow control. Prefer a stable path
/// (`/dev/serial/by-id/...`): it survives re-enumeration after an unplug.
#[derive(Debug, Clone, PartialEq)]
pub struct SerialPath {
    /// The device path.
    pub path: String,
    /// Line rate.
    pub baud: u32,
}

impl Connector for SerialPath {
    fn describe(&self) -> String {
        self.path.clone()
    }

    fn open(&self) -> OpenFuture<'_> {
        Box::pin(async move {
            let builder = tokio_serial::new(&self.path, self.baud)
                .data_bits(tokio_serial::DataBits::Eight)
                .parity(tokio_serial::Parity::None)
                .stop_bits(tokio_serial::StopBits::One)
                .flow_control(tokio_serial::FlowControl::None);
            let port = tokio_serial::SerialStream::open(&builder).map_err(io::Error::from)?;
            Ok(Box::new(port) as BoxIo)
        })
    }
}

/// Any function that opens a byte stream (for simulators and tests).
pub struct FnConnector<F> {
    name: String,
    open: F,
}

impl<F> FnConnector<F> {
    /// Named `name`, opening with `open`.
    pub fn new(name: impl Into<String>, open: F) -> Self {
        FnConnector {
            name: name.into(),
            open,
        }
    }
}

impl<F, Fut> Connector for FnConnector<F>
where
    F: Fn() -> Fut + Send + Sync,
    Fut: Future<Output = io::Result<BoxIo>> + Send + 'static,
{
    fn describe(&self) -> String {
        self.name.clone()
    }

    fn open(&self) -> OpenFuture<'_> {
        Box::pin((self.open)())
    }
}

/// Deadlines and retries of a driver. Every operation ends within
/// [`Policy::worst_case`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Policy {
    /// Opening the port.
    pub open_timeout: Duration,
    /// A query's reply.
    pub query_timeout: Duration,
    /// A move's completion (from the command to the motion-done reply).
    pub move_timeout: Duration,
    /// Homing's completion.
    pub home_timeout: Duration,
    /// Attempts of an idempotent request (1 = no retry).
    pub attempts: u32,
    /// Wait before the first retry; doubled before each further one.
    pub backoff: Duration,
}

impl Policy {
    /// An upper bound on any one operation (reconnect, home, move and readback, each attempt
    /// with its backoff).
    pub fn worst_case(&self) -> Duration {
        let backoff: Duration = (0..self.attempts)
            .map(|k| self.backoff * 2u32.saturating_pow(k))
            .sum();
        let attempt = self.move_timeout + self.home_timeout + 4 * self.query_timeout;
        self.open_timeout + attempt * self.attempts * 2 + backoff
    }

    /// The wait before retry number `k` (from 0).
    pub fn backoff(&self, k: u32) -> Duration {
        self.backoff * 2u32.saturating_pow(k.min(16))
    }

    /// Waits before attempt `k` (from 0): nothing before the first, the backoff before the rest.
    pub async fn pause_before(&self, attempt: u32) {
        if attempt > 0 {
            tokio::time::sleep(self.backoff(attempt - 1)).await;
        }
    }

    /// Identifies (and homes) a session while it needs it: up to [`Policy::attempts`] tries,
    /// each after [`Policy::pause_before`]; a [`retryable`] error is kept and tried again,
    /// any other is returned at once. The last retryable error (or the session's
    /// [`Initialise::init_failed`]) is returned when every attempt is spent.
    pub(crate) async fn retry_init<S: Initialise>(
        &self,
        session: &mut S,
    ) -> Result<(), DeviceError> {
        let mut last = None;
        for k in 0..self.attempts.max(1) {
            if !session.needs_init() {
                return Ok(());
            }
            self.pause_before(k).await;
            match session.init_attempt().await {
                Ok(()) => {}
                Err(e) if retryable(&e) => last = Some(e),
                Err(e) => return Err(e),
            }
        }
        if session.needs_init() {
            return Err(last.unwrap_or_else(|| session.init_failed()));
        }
        Ok(())
    }
}

/// Whether a failed request may be sent again: a timeout, a garbled or unexpected reply, a
/// busy device or a stall (not a disconnect, which reopens the port, nor a refused request).
pub(crate) fn retryable(e: &DeviceError) -> bool {
    matches!(
        e.kind(),
        ErrorKind::Timeout | ErrorKind::Protocol | ErrorKind::Busy | ErrorKind::Stalled
    )
}

/// A dialect session that identifies (and homes) its device after the port opens or the
/// device resets; [`Policy::retry_init`] drives it.
pub(crate) trait Initialise: Send {
    /// Whether the device still has to be identified.
    fn needs_init(&self) -> bool;
    /// One attempt to identify (and home); on success the session no longer needs it (unless
    /// the attempt itself saw a reset).
    fn init_attempt(&mut self) -> impl Future<Output = Result<(), DeviceError>> + Send;
    /// The error when the attempts ran out without a retryable error to report.
    fn init_failed(&self) -> DeviceError;
}

/// Implements [`Initialise`] for a session with a `needs_init: bool` field, an inherent
/// `async fn init(&mut self) -> Result<(), DeviceError>` and an inherent
/// `fn error(&self, ErrorKind, message) -> DeviceError`: a successful `init` clears the flag.
macro_rules! initialise_by_flag {
    ($session:ty) => {
        impl $crate::link::Initialise for $session {
            fn needs_init(&self) -> bool {
                self.needs_init
            }

            async fn init_attempt(&mut self) -> Result<(), polar_hal::DeviceError> {
                self.init().await?;
                self.needs_init = false;
                Ok(())
            }

            fn init_failed(&self) -> polar_hal::DeviceError {
                self.error(polar_hal::ErrorKind::Other, "init failed")
            }
        }
    };
}
pub(crate) use initialise_by_flag;

/// An open-or-closed port with a receive buffer.
pub struct Link {
    connector: Box<dyn Connector>,
    io: Option<BoxIo>,
    rx: Vec<u8>,
    opens: u32,
}

impl Link {
    /// A closed link on `connector`.
    pub fn new(connector: Box<dyn Connector>) -> Self {
        Link {
            connector,
            io: None,
            rx: Vec::new(),
            opens: 0,
        }
    }

    /// The port's name.
    pub fn name(&self) -> String {
        self.connector.describe()
    }

    /// Whether the port is open.
    pub fn is_open(&self) -> bool {
        self.io.is_some()
    }

    /// How many times the port has been opened.
    pub fn opens(&self) -> u32 {
        self.opens
    }

    /// An error of `kind` on this port.
    pub fn error(&self, kind: ErrorKind, message: impl Into<String>) -> DeviceError {
        DeviceError::new(kind, self.name(), message)
    }

    /// Opens the port (closing it first if open). A port that cannot be opened is
    /// [`ErrorKind::Disconnected`]; one held by another program is [`ErrorKind::Busy`].
    pub async fn open(&mut self, timeout: Duration) -> Result<(), DeviceError> {
        self.close();
        let opened = tokio::time::timeout(timeout, self.connector.open()).await;
        match opened {
            Ok(Ok(io)) => {
                self.io = Some(io);
                self.opens += 1;
                tracing::debug!(port = %self.name(), "opened");
                Ok(())
            }
            Ok(Err(e)) if e.kind() == io::ErrorKind::ResourceBusy => Err(self.error(
                ErrorKind::Busy,
                format!("the port is in use by another program: {e}"),
            )),
            Ok(Err(e)) => Err(self.error(
                ErrorKind::Disconnected,
                format!("cannot open the port: {e}"),
            )),
            Err(_) => Err(self.error(
                ErrorKind::Disconnected,
                format!("opening the port took longer than {timeout:?}"),
            )),
        }
    }

    /// Closes the port and forgets buffered input.
    pub fn close(&mut self) {
        self.io = None;
        self.rx.clear();
    }

    fn lost(&mut self, what: &str, e: Option<io::Error>) -> DeviceError {
        self.close();
        let detail = e.map_or_else(|| "end of file".to_string(), |e| e.to_string());
        tracing::warn!(port = %self.name(), "device lost while {what}: {detail}");
        self.error(
            ErrorKind::Disconnected,
            format!("device lost while {what} ({detail})"),
        )
    }

    /// Writes all of `bytes` within `timeout`.
    pub async fn write(&mut self, bytes: &[u8], timeout: Duration) -> Result<(), DeviceError> {
        let Some(io) = self.io.as_mut() else {
            return Err(self.error(ErrorKind::Disconnected, "the port is closed"));
        };
        let written = tokio::time::timeout(timeout, async {
            io.write_all(bytes).await?;
            io.flush().await
        })
        .await;
        match written {
            Ok(Ok(())) => Ok(()),
            Ok(Err(e)) => Err(self.lost("writing", Some(e))),
            Err(_) => Err(self.error(
                ErrorKind::Timeout,
                format!("writing {} bytes took longer than {timeout:?}", bytes.len()),
            )),
        }
    }

    /// Reads whatever arrives next into the buffer, waiting until `deadline` at most.
    pub async fn fill(&mut self, deadline: Instant, waiting_for: &str) -> Result<(), DeviceError> {
        let Some(io) = self.io.as_mut() else {
            return Err(self.error(ErrorKind::Disconnected, "the port is closed"));
        };
        let mut buf = [0u8; 256];
        match tokio::time::timeout_at(deadline, io.read(&mut buf)).await {
            Ok(Ok(0)) => Err(self.lost("reading", None)),
            Ok(Ok(n)) => {
                self.rx.extend_from_slice(&buf[..n]);
                Ok(())
            }
            Ok(Err(e)) => Err(self.lost("reading", Some(e))),
            Err(_) => Err(self.error(
                ErrorKind::Timeout,
                format!("no {waiting_for} before the deadline"),
            )),
        }
    }

    /// The received bytes not consumed yet.
    pub fn buffer(&mut self) -> &mut Vec<u8> {
        &mut self.rx
    }

    /// Drops buffered input and whatever is already waiting in the port (stale bytes from a
    /// late reply or a boot banner), without waiting for more.
    pub async fn discard_input(&mut self) -> Result<usize, DeviceError> {
        let mut dropped = std::mem::take(&mut self.rx).len();
        let Some(io) = self.io.as_mut() else {
            return Ok(dropped);
        };
        let mut buf = [0u8; 256];
        loop {
            // The read is polled once: what is waiting is taken, nothing is awaited. (A zero
            // timeout would wait for tokio's next millisecond timer tick.)
            let polled = std::future::poll_fn(|cx| {
                let mut read = tokio::io::ReadBuf::new(&mut buf);
                std::task::Poll::Ready(match Pin::new(&mut *io).poll_read(cx, &mut read) {
                    std::task::Poll::Ready(r) => Some(r.map(|()| read.filled().len())),
                    std::task::Poll::Pending => None,
                })
            })
            .await;
            match polled {
                Some(Ok(0)) => return Err(self.lost("discarding input", None)),
                Some(Ok(n)) => dropped += n,
                Some(Err(e)) => return Err(self.lost("discarding input", Some(e))),
                None => return Ok(dropped),
            }
        }
    }
}
