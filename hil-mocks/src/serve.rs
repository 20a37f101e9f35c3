//! Serves a [`Simulator`] on a byte stream, the way a USB-serial cable would: over a real
//! pseudo-terminal pair (so the drivers' real serial code runs) or over an in-memory pipe (fast
//! tests on tokio's paused clock). The server owns the simulated device, maps tokio's clock onto
//! its simulated time, paces its output at the device's baud rate and applies the transport
//! faults of [`FaultProfile`]: chunked and coalesced reads, latency, late replies, line noise,
//! stale bytes at open, and unplug with replug (power-cycled, at a new pseudo-terminal).
//!
//! A pseudo-terminal device is reached through a stable symbolic link (like
//! `/dev/serial/by-id/...`) that is re-pointed when the device comes back after an unplug.

use crate::faults::{Dice, FaultProfile};
use crate::simulator::{Simulator, Truth};
use std::io;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt, DuplexStream};
use tokio::sync::{mpsc, oneshot, watch};
use tokio::task::JoinHandle;
use tokio::time::{Duration, Instant};

/// Counters of what the server did, for tests and benchmarks.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ServeStats {
    /// Connections served (opens of the port).
    pub connections: u32,
    /// Bytes received from the host.
    pub bytes_in: u64,
    /// Bytes sent to the host.
    pub bytes_out: u64,
    /// Unplugs injected.
    pub unplugs: u32,
    /// Replies delivered late.
    pub late_replies: u32,
}

struct Shared {
    sim: Mutex<Box<dyn Simulator>>,
    stats: Mutex<ServeStats>,
    start: Instant,
    port: Mutex<Option<String>>,
}

impl Shared {
    fn now_s(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }

    fn at(&self, t_s: f64) -> Instant {
        self.start + Duration::from_secs_f64(t_s.max(0.0))
    }

    fn sim(&self) -> MutexGuard<'_, Box<dyn Simulator>> {
        // A panic while the lock was held is a bug elsewhere; the state is still usable.
        self.sim.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn stats(&self) -> MutexGuard<'_, ServeStats> {
        self.stats.lock().unwrap_or_else(|e| e.into_inner())
    }
}

type ConnectRequest = oneshot::Sender<io::Result<DuplexStream>>;

/// Opens in-memory connections to a served device (what opening the port is for a pty).
#[derive(Clone)]
pub struct MemoryPort {
    requests: mpsc::Sender<ConnectRequest>,
}

impl MemoryPort {
    /// Opens the port: a new connection replaces the previous one. Fails with
    /// [`io::ErrorKind::NotFound`] while the device is unplugged.
    pub async fn open(&self) -> io::Result<DuplexStream> {
        let (tx, rx) = oneshot::channel();
        let gone = || io::Error::new(io::ErrorKind::NotFound, "simulator stopped");
        self.requests.send(tx).await.map_err(|_| gone())?;
        rx.await.map_err(|_| gone())?
    }
}

/// The ground truth of a served device, shareable across threads.
#[derive(Clone)]
pub struct TruthHandle(Arc<Shared>);

impl TruthHandle {
    /// Where the mechanism really is now.
    pub fn truth(&self) -> Truth {
        let now = self.0.now_s();
        self.0.sim().truth(now)
    }
}

/// A running simulated device. Dropping it stops the server (and removes a pty's link, and
/// the link's folder when [`SimServer::pty_in_new_dir`] made it).
pub struct SimServer {
    shared: Arc<Shared>,
    memory: Option<MemoryPort>,
    link: Option<PathBuf>,
    made_dir: Option<PathBuf>,
    stop: watch::Sender<bool>,
    unplug: mpsc::UnboundedSender<f64>,
    task: Option<JoinHandle<()>>,
}

enum Source {
    Memory(mpsc::Receiver<ConnectRequest>),
    Pty(PathBuf),
}

impl SimServer {
    /// Serves `sim` over in-memory connections ([`SimServer::memory_port`]). Needs a tokio
    /// runtime; works on a paused clock.
    pub fn memory(sim: impl Simulator, faults: FaultProfile, seed: u64) -> SimServer {
        let (tx, rx) = mpsc::channel(4);
        let mut server = SimServer::spawn(Box::new(sim), faults, seed, Source::Memory(rx), None);
        server.memory = Some(MemoryPort { requests: tx });
        server
    }

    /// Serves `sim` on a new pseudo-terminal pair, reachable through the symbolic link `link`
    /// (created or replaced; its directory must exist). Needs a tokio runtime with I/O enabled.
    pub fn pty(
        sim: impl Simulator,
        faults: FaultProfile,
        seed: u64,
        link: &Path,
    ) -> io::Result<SimServer> {
        let pair = open_pty(link)?;
        let mut server = SimServer::spawn(
            Box::new(sim),
            faults,
            seed,
            Source::Pty(link.to_path_buf()),
            Some(pair),
        );
        server.link = Some(link.to_path_buf());
        Ok(server)
    }

    /// [`SimServer::pty`] with its link in a new folder `dir` (made here, which must not exist
    /// yet): dropping or shutting down the server removes the link and the folder, so no
    /// stopped simulator leaves a trace in the temporary directory.
    pub fn pty_in_new_dir(
        sim: impl Simulator,
        faults: FaultProfile,
        seed: u64,
        dir: &Path,
        name: &str,
    ) -> io::Result<SimServer> {
        std::fs::create_dir(dir)?;
        match SimServer::pty(sim, faults, seed, &dir.join(name)) {
            Ok(mut server) => {
                server.made_dir = Some(dir.to_path_buf());
                Ok(server)
            }
            Err(e) => {
                let _ = std::fs::remove_dir_all(dir);
                Err(e)
            }
        }
    }

    fn spawn(
        sim: Box<dyn Simulator>,
        faults: FaultProfile,
        seed: u64,
        source: Source,
        first_pty: Option<PtyPair>,
    ) -> SimServer {
        let port = first_pty.as_ref().map(|p| p.path.clone());
        let shared = Arc::new(Shared {
            sim: Mutex::new(sim),
            stats: Mutex::new(ServeStats::default()),
            start: Instant::now(),
            port: Mutex::new(port),
        });
        let (stop, stopped) = watch::channel(false);
        let (unplug, unplugs) = mpsc::unbounded_channel();
        let task = tokio::spawn(run(
            shared.clone(),
            source,
            first_pty,
            faults,
            seed,
            stopped,
            unplugs,
        ));
        SimServer {
            shared,
            memory: None,
            link: None,
            made_dir: None,
            stop,
            unplug,
            task: Some(task),
        }
    }

    /// The in-memory port (for a server made with [`SimServer::memory`]).
    pub fn memory_port(&self) -> Option<MemoryPort> {
        self.memory.clone()
    }

    /// The stable link a pty server is reached through.
    pub fn link(&self) -> Option<&Path> {
        self.link.as_deref()
    }

    /// The pseudo-terminal the device is on now (`None` while unplugged or in memory).
    pub fn port(&self) -> Option<String> {
        self.shared
            .port
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// Simulated time now, seconds since the server started.
    pub fn now_s(&self) -> f64 {
        self.shared.now_s()
    }

    /// Where the mechanism really is now.
    pub fn truth(&self) -> Truth {
        let now = self.shared.now_s();
        self.shared.sim().truth(now)
    }

    /// A handle on the device's ground truth that outlives borrows of the server (for the
    /// simulated camera, which reads the analyzer's true angle at every exposure).
    pub fn truth_handle(&self) -> TruthHandle {
        TruthHandle(Arc::clone(&self.shared))
    }

    /// What the device is.
    pub fn describe(&self) -> String {
        self.shared.sim().describe()
    }

    /// Counters so far.
    pub fn stats(&self) -> ServeStats {
        *self.shared.stats()
    }

    /// Unplugs the device now; it comes back power-cycled (at a new pseudo-terminal, behind the
    /// same link) after `away_s` seconds.
    pub fn unplug(&self, away_s: f64) {
        let _ = self.unplug.send(away_s.clamp(0.0, 3600.0));
    }

    /// Stops serving and waits for the server to end.
    pub async fn shutdown(mut self) {
        let _ = self.stop.send(true);
        if let Some(task) = self.task.take() {
            let _ = task.await;
        }
    }
}

impl Drop for SimServer {
    fn drop(&mut self) {
        let _ = self.stop.send(true);
        if let Some(task) = self.task.take() {
            task.abort();
        }
        if let Some(link) = &self.link {
            let _ = std::fs::remove_file(link);
        }
        if let Some(dir) = &self.made_dir {
            let _ = std::fs::remove_dir_all(dir);
        }
    }
}

/// A pseudo-terminal pair: the device side, the host side kept open (so the pty stays raw and
/// alive while no host has it open), and the host side's path.
struct PtyPair {
    device: tokio_serial::SerialStream,
    _host: tokio_serial::SerialStream,
    path: String,
}

fn open_pty(link: &Path) -> io::Result<PtyPair> {
    use tokio_serial::SerialPort;
    let (device, host) = tokio_serial::SerialStream::pair().map_err(io::Error::from)?;
    let path = host
        .name()
        .ok_or_else(|| io::Error::other("the pseudo-terminal has no name"))?;
    // Re-point the link atomically: make a new link beside it and rename it over the old one.
    let tmp = link.with_extension("new");
    let _ = std::fs::remove_file(&tmp);
    std::os::unix::fs::symlink(&path, &tmp)?;
    std::fs::rename(&tmp, link)?;
    Ok(PtyPair {
        device,
        _host: host,
        path,
    })
}

/// Output waiting to be delivered: (due time, bytes), sorted by due time.
struct Outbox {
    queue: Vec<(f64, Vec<u8>)>,
    line_free_s: f64,
    seconds_per_byte: f64,
}

impl Outbox {
    fn new(seconds_per_byte: f64) -> Self {
        Outbox {
            queue: Vec::new(),
            line_free_s: 0.0,
            seconds_per_byte,
        }
    }

    fn insert(&mut self, due: f64, bytes: Vec<u8>) {
        let at = self.queue.partition_point(|(t, _)| *t <= due);
        self.queue.insert(at, (due, bytes));
    }

    /// Queues a reply through the transport faults.
    fn push(
        &mut self,
        now_s: f64,
        mut bytes: Vec<u8>,
        faults: &FaultProfile,
        dice: &mut Dice,
        stats: &mut ServeStats,
    ) {
        if bytes.is_empty() {
            return;
        }
        if dice.chance(faults.garbage) {
            let n = 1 + dice.index(8);
            let mut noisy: Vec<u8> = (0..n).map(|_| dice.byte()).collect();
            noisy.append(&mut bytes);
            bytes = noisy;
        }
        let mut due = now_s + faults.latency_s;
        if dice.chance(faults.coalesce_replies) {
            due += 0.05 * dice.uniform();
        }
        if dice.chance(faults.late_reply) {
            // A late reply does not hold up the line for what follows.
            stats.late_replies += 1;
            self.insert(due + faults.late_by_s, bytes);
            return;
        }
        let pieces: Vec<Vec<u8>> = if dice.chance(faults.chunk_reads) {
            let mut pieces = Vec::new();
            let mut rest = &bytes[..];
            while !rest.is_empty() {
                let n = (1 + dice.index(4)).min(rest.len());
                pieces.push(rest[..n].to_vec());
                rest = &rest[n..];
            }
            pieces
        } else {
            vec![bytes]
        };
        for piece in pieces {
            let start = due.max(self.line_free_s);
            self.line_free_s = start + piece.len() as f64 * self.seconds_per_byte;
            self.insert(self.line_free_s, piece);
            if faults.chunk_reads > 0.0 {
                due = self.line_free_s + 0.002 * dice.uniform();
            }
        }
    }

    fn next_due(&self) -> Option<f64> {
        self.queue.first().map(|(t, _)| *t)
    }

    fn take_due(&mut self, now_s: f64) -> Vec<u8> {
        let n = self.queue.partition_point(|(t, _)| *t <= now_s);
        self.queue.drain(..n).flat_map(|(_, b)| b).collect()
    }
}

/// The host's bytes on their way to the device: a pseudo-terminal hands them over at once, but
/// on the device's serial line they take their bits' time at its baud, and the device acts on
/// a request only once its last byte is in.
struct Inbox {
    queue: std::collections::VecDeque<(f64, Vec<u8>)>,
    line_free_s: f64,
    seconds_per_byte: f64,
}

impl Inbox {
    fn new(seconds_per_byte: f64) -> Self {
        Inbox {
            queue: std::collections::VecDeque::new(),
            line_free_s: 0.0,
            seconds_per_byte,
        }
    }

    /// Bytes the host wrote at `now_s`: in at the device once the line has carried them.
    fn push(&mut self, now_s: f64, bytes: &[u8]) {
        let start = now_s.max(self.line_free_s);
        self.line_free_s = start + bytes.len() as f64 * self.seconds_per_byte;
        self.queue.push_back((self.line_free_s, bytes.to_vec()));
    }

    fn next_due(&self) -> Option<f64> {
        self.queue.front().map(|(t, _)| *t)
    }

    /// The oldest bytes in by `now_s`, with the time they were in.
    fn pop_due(&mut self, now_s: f64) -> Option<(f64, Vec<u8>)> {
        if self.queue.front().is_some_and(|(t, _)| *t <= now_s) {
            self.queue.pop_front()
        } else {
            None
        }
    }
}

trait Stream: AsyncRead + AsyncWrite + Unpin + Send {}
impl<T: AsyncRead + AsyncWrite + Unpin + Send> Stream for T {}

enum Ended {
    /// An unplug (a fault, or requested), away for this many seconds.
    Unplugged(f64),
    /// The host closed the connection (in memory) or the pty failed.
    Closed,
    /// The host opened the port again (in memory): serve the new connection.
    Reopened(ConnectRequest),
    /// The server is stopping.
    Stop,
}

async fn run(
    shared: Arc<Shared>,
    mut source: Source,
    mut first_pty: Option<PtyPair>,
    faults: FaultProfile,
    seed: u64,
    mut stopped: watch::Receiver<bool>,
    mut unplugs: mpsc::UnboundedReceiver<f64>,
) {
    let mut dice = Dice::new(seed ^ 0x7472_616e_7370_6f72);
    let mut pending: Option<ConnectRequest> = None;
    let mut last_path: Option<String> = None;
    loop {
        // A connection.
        let (stream, host_side): (Box<dyn Stream>, Option<tokio_serial::SerialStream>) =
            match &mut source {
                Source::Memory(requests) => {
                    let request = match pending.take() {
                        Some(r) => r,
                        None => tokio::select! {
                            r = requests.recv() => match r { Some(r) => r, None => return },
                            _ = stopped.changed() => return,
                        },
                    };
                    let (host, device) = tokio::io::duplex(4096);
                    if request.send(Ok(host)).is_err() {
                        continue;
                    }
                    (Box::new(device), None)
                }
                Source::Pty(link) => {
                    // A re-enumerated USB device usually comes back under a new name (ttyUSB0
                    // becomes ttyUSB1); the kernel would hand out the freed pty number again,
                    // so pairs with the old name are held until a new one is made.
                    let pair = match first_pty.take() {
                        Some(p) => p,
                        None => {
                            let mut held = Vec::new();
                            loop {
                                match open_pty(link) {
                                    Ok(p)
                                        if Some(&p.path) == last_path.as_ref()
                                            && held.len() < 8 =>
                                    {
                                        held.push(p)
                                    }
                                    Ok(p) => break p,
                                    Err(e) => {
                                        tracing::error!(
                                            "simulator: cannot open a pseudo-terminal: {e}"
                                        );
                                        return;
                                    }
                                }
                            }
                        }
                    };
                    last_path = Some(pair.path.clone());
                    *shared.port.lock().unwrap_or_else(|e| e.into_inner()) =
                        Some(pair.path.clone());
                    (Box::new(pair.device), Some(pair._host))
                }
            };
        shared.stats().connections += 1;
        let ended = serve(
            &shared,
            stream,
            &mut source,
            &faults,
            &mut dice,
            &mut stopped,
            &mut unplugs,
        )
        .await;
        match ended {
            Ended::Stop => return,
            Ended::Closed => {
                if matches!(source, Source::Pty(_)) {
                    return;
                }
            }
            Ended::Reopened(request) => pending = Some(request),
            Ended::Unplugged(away_s) => {
                shared.stats().unplugs += 1;
                *shared.port.lock().unwrap_or_else(|e| e.into_inner()) = None;
                drop(host_side);
                let back = Instant::now() + Duration::from_secs_f64(away_s);
                // While away, opens fail.
                loop {
                    let request = match &mut source {
                        Source::Memory(requests) => tokio::select! {
                            r = requests.recv() => r,
                            _ = tokio::time::sleep_until(back) => break,
                            _ = stopped.changed() => return,
                        },
                        Source::Pty(_) => tokio::select! {
                            _ = tokio::time::sleep_until(back) => break,
                            _ = stopped.changed() => return,
                        },
                    };
                    match request {
                        Some(r) => {
                            let _ = r.send(Err(io::Error::new(
                                io::ErrorKind::NotFound,
                                "the simulated device is unplugged",
                            )));
                        }
                        None => return,
                    }
                }
                let now = shared.now_s();
                shared.sim().power_cycle(now);
            }
        }
    }
}

/// Sleeps until `wake`. tokio's timer fires on its next millisecond tick, up to 1 ms late;
/// a device on a real line is not, so with `precise` (a pseudo-terminal, on the real clock)
/// the last 2 ms are slept by a blocking thread, to within microseconds. In
/// memory (tokio's clock, maybe paused) the timer is the clock, and is used as it is.
async fn sleep_until(wake: Instant, precise: bool) {
    const COARSE: Duration = Duration::from_millis(2);
    if !precise {
        return tokio::time::sleep_until(wake).await;
    }
    if let Some(early) = wake.checked_sub(COARSE) {
        if early > Instant::now() {
            tokio::time::sleep_until(early).await;
        }
    }
    let left = wake.saturating_duration_since(Instant::now());
    if !left.is_zero() {
        // An abandoned sleep (a read came first) ends by itself within 2 ms.
        let until = std::time::Instant::now() + left;
        let slept = tokio::task::spawn_blocking(move || crate::sleep_until_precisely(until)).await;
        if slept.is_err() {
            tokio::time::sleep_until(wake).await;
        }
    }
}

async fn serve(
    shared: &Shared,
    mut stream: Box<dyn Stream>,
    source: &mut Source,
    faults: &FaultProfile,
    dice: &mut Dice,
    stopped: &mut watch::Receiver<bool>,
    unplugs: &mut mpsc::UnboundedReceiver<f64>,
) -> Ended {
    let now = shared.now_s();
    let mut outbox = Outbox::new(shared.sim().seconds_per_byte());
    let stale: Vec<u8> = (0..faults.stale_bytes_at_open)
        .map(|_| dice.byte())
        .collect();
    outbox.insert(now, stale);
    let opened = shared.sim().on_open(now);
    {
        let mut stats = shared.stats();
        outbox.push(now, opened, faults, dice, &mut stats);
    }
    let mut inbox = Inbox::new(shared.sim().seconds_per_byte());
    let mut buf = [0u8; 256];
    loop {
        let now = shared.now_s();
        while let Some((in_s, bytes)) = inbox.pop_due(now) {
            let reply = shared.sim().receive(in_s, &bytes);
            outbox.push(in_s, reply, faults, dice, &mut shared.stats());
            if dice.chance(faults.unplug) {
                return Ended::Unplugged(faults.replug_s);
            }
        }
        let ticked = shared.sim().tick(now);
        outbox.push(now, ticked, faults, dice, &mut shared.stats());
        let due = outbox.take_due(now);
        if !due.is_empty() {
            shared.stats().bytes_out += due.len() as u64;
            if stream.write_all(&due).await.is_err() || stream.flush().await.is_err() {
                return Ended::Closed;
            }
        }
        let next = [
            outbox.next_due(),
            inbox.next_due(),
            shared.sim().next_event_s(),
        ]
        .into_iter()
        .flatten()
        .fold(f64::INFINITY, f64::min);
        let wake = if next.is_finite() {
            // One microsecond late, so that the float-to-instant rounding never wakes the
            // server just before the event (which would spin without advancing a paused clock).
            shared.at(next) + Duration::from_micros(1)
        } else {
            Instant::now() + Duration::from_secs(3600)
        };
        let precise = matches!(source, Source::Pty(_));
        let reopen = async {
            match source {
                Source::Memory(requests) => requests.recv().await,
                Source::Pty(_) => std::future::pending().await,
            }
        };
        tokio::select! {
            read = stream.read(&mut buf) => {
                let n = match read {
                    Ok(0) | Err(_) => return Ended::Closed,
                    Ok(n) => n,
                };
                shared.stats().bytes_in += n as u64;
                inbox.push(shared.now_s(), &buf[..n]);
            }
            _ = sleep_until(wake, precise) => {}
            request = reopen => match request {
                Some(r) => return Ended::Reopened(r),
                None => return Ended::Stop,
            },
            Some(away_s) = unplugs.recv() => return Ended::Unplugged(away_s),
            _ = stopped.changed() => return Ended::Stop,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::native::{NativeConfig, NativeDevice};
    use polar_firmware_protocol::{encode_vec, Command, Decoder, Reply};

    async fn read_replies(io: &mut DuplexStream, n: usize) -> Vec<Reply> {
        let mut decoder = Decoder::<Reply>::new();
        let mut out = Vec::new();
        let mut buf = [0u8; 64];
        while out.len() < n {
            let k = io.read(&mut buf).await.unwrap();
            assert!(k > 0, "closed");
            for &b in &buf[..k] {
                if let Some(Ok(p)) = decoder.feed(b) {
                    out.push(p.message);
                }
            }
        }
        out
    }

    /// In memory on the paused clock: the boot notice at open, an identify answered after the
    /// request's and the reply's transmission times at 115200 baud (and not before), and a home
    /// whose MotionDone arrives at the simulated homing time (0.5 s), late only by the sending
    /// times and timer rounding.
    #[tokio::test(start_paused = true)]
    async fn memory_round_trip_paced_and_timed() {
        let server = SimServer::memory(
            NativeDevice::new(NativeConfig::rotator(), FaultProfile::default(), 1),
            FaultProfile::default(),
            1,
        );
        let mut io = server.memory_port().unwrap().open().await.unwrap();
        assert!(matches!(
            read_replies(&mut io, 1).await[..],
            [Reply::Boot { .. }]
        ));
        let t0 = Instant::now();
        io.write_all(&encode_vec(1, &Command::Identify))
            .await
            .unwrap();
        let r = read_replies(&mut io, 1).await;
        assert!(matches!(r[..], [Reply::Identity { .. }]), "{r:?}");
        let dt = t0.elapsed().as_secs_f64();
        // The request's bytes, then the identity frame's 21: 10 bits each at 115200 baud. The
        // device waits for the request's last byte, and tokio's timer rounds each of the two
        // wake-ups up to the next millisecond.
        let request = encode_vec(1, &Command::Identify).len();
        let wire_s = (request + 21) as f64 * 10.0 / 115_200.0;
        assert!(
            dt >= wire_s && dt < wire_s + 2e-3,
            "{dt} s, on the wire {wire_s} s"
        );
        let t0 = Instant::now();
        io.write_all(&encode_vec(2, &Command::Home)).await.unwrap();
        let r = read_replies(&mut io, 2).await;
        assert!(
            matches!(r[..], [Reply::Ack, Reply::MotionDone { .. }]),
            "{r:?}"
        );
        let dt = t0.elapsed().as_secs_f64();
        // The frames take 1.5 ms to send and tokio's timer rounds each wake up to the next
        // millisecond: 0.5 s + [0, 4 ms).
        assert!((0.5..0.504).contains(&dt), "{dt}");
        assert_eq!(server.stats().connections, 1);
    }

    /// Unplug: the connection closes, opens fail with NotFound for `replug_s`, then succeed
    /// with the device power-cycled (a boot notice again).
    #[tokio::test(start_paused = true)]
    async fn unplug_and_replug_in_memory() {
        let faults = FaultProfile {
            unplug: 1.0,
            replug_s: 1.0,
            ..Default::default()
        };
        let server = SimServer::memory(
            NativeDevice::new(NativeConfig::rotator(), FaultProfile::default(), 1),
            faults,
            2,
        );
        let port = server.memory_port().unwrap();
        let mut io = port.open().await.unwrap();
        read_replies(&mut io, 1).await;
        io.write_all(&encode_vec(1, &Command::Identify))
            .await
            .unwrap();
        let mut buf = [0u8; 64];
        // The host sees end of file (what tokio reports for an unplugged tty).
        let mut got = 0;
        loop {
            match io.read(&mut buf).await {
                Ok(0) | Err(_) => break,
                Ok(n) => got += n,
            }
        }
        assert_eq!(got, 0, "no reply from a device unplugged on receipt");
        let e = port.open().await.unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::NotFound);
        tokio::time::sleep(Duration::from_secs_f64(1.1)).await;
        let mut io = port.open().await.unwrap();
        assert!(matches!(
            read_replies(&mut io, 1).await[..],
            [Reply::Boot { .. }]
        ));
        assert_eq!(server.stats().unplugs, 1);
    }

    /// Over a real pseudo-terminal, opened through the stable link as a driver would: the boot
    /// notice and an identify come back.
    #[tokio::test]
    async fn pty_round_trip_through_the_link() {
        let dir = std::env::temp_dir().join(format!("polar-serve-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let link = dir.join("native0");
        let server = SimServer::pty(
            NativeDevice::new(NativeConfig::rotator(), FaultProfile::default(), 1),
            FaultProfile::default(),
            1,
            &link,
        )
        .unwrap();
        let target = std::fs::read_link(&link).unwrap();
        assert_eq!(Some(target.to_string_lossy().into_owned()), server.port());
        let mut port =
            tokio_serial::SerialStream::open(&tokio_serial::new(link.to_string_lossy(), 115_200))
                .unwrap();
        port.write_all(&encode_vec(1, &Command::Identify))
            .await
            .unwrap();
        let mut decoder = Decoder::<Reply>::new();
        let mut seen = Vec::new();
        let mut buf = [0u8; 64];
        let deadline = Instant::now() + Duration::from_secs(5);
        while seen.len() < 2 && Instant::now() < deadline {
            let n = tokio::time::timeout(Duration::from_secs(5), port.read(&mut buf))
                .await
                .unwrap()
                .unwrap();
            for &b in &buf[..n] {
                if let Some(Ok(p)) = decoder.feed(b) {
                    seen.push(p.message);
                }
            }
        }
        assert!(
            matches!(seen[..], [Reply::Boot { .. }, Reply::Identity { .. }]),
            "{seen:?}"
        );
        drop(server);
        assert!(!link.exists());
    }
}
