//! Our firmware's stage and wheel (`firmware-protocol/SPEC.md`).
//!
//! * Replies are matched to requests by sequence number, so a late or duplicated reply to an
//!   earlier request, a corrupted frame or line noise is skipped, never mistaken for the answer.
//! * A boot notice (frame with sequence 0) at any time means the controller reset: the driver
//!   re-identifies and re-homes before the next motion, and a motion in flight is repeated.
//! * Queries and absolute moves are idempotent and retried with backoff; relative moves are
//!   never sent. A move whose acknowledgement or completion is lost is judged by the position
//!   read back, never by the absence of an error.

use crate::any::{AnyRotator, AnyWheel};
use crate::dialect::{self, Dialect, Position, LINE_8N1};
use crate::link::{retryable, Connector, Initialise, Link, Policy};
use polar_firmware_protocol::{
    encode_vec, next_seq, Command, Decoder, DeviceKind, ErrorCode, Packet, Reply, StatusFlags,
    PROTOCOL_VERSION,
};
use polar_hal::{
    angle_from_counts, counts_toward, ContinuousSupport, DeviceError, ErrorKind, FilterWheel,
    Rotator, RotatorInfo, WireTimes, TURN_RAD,
};
use std::collections::VecDeque;
use std::time::Duration;
use tokio::time::Instant;

/// The default policy for our firmware at 115200 baud.
pub fn default_policy() -> Policy {
    Policy {
        open_timeout: Duration::from_secs(2),
        query_timeout: Duration::from_millis(200),
        move_timeout: Duration::from_secs(15),
        home_timeout: Duration::from_secs(30),
        attempts: 4,
        backoff: Duration::from_millis(20),
    }
}

/// What the controller said about itself.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Identity {
    /// Firmware version.
    pub firmware: [u8; 3],
    /// Rotator or wheel.
    pub device: DeviceKind,
    /// Encoder counts per output turn.
    pub counts_per_turn: u32,
    /// Slots (wheels).
    pub slots: u8,
    /// Serial number.
    pub serial: u32,
}

pub use polar_hal::TriggerPulse;

/// A status reading.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Status {
    position_counts: i32,
    flags: StatusFlags,
    slot: u8,
}

/// A connection to one controller: sequence numbers, decoder, reset handling, retries.
pub struct NativeSession {
    link: Link,
    policy: Policy,
    kind: DeviceKind,
    seq: u8,
    decoder: Decoder<Reply>,
    packets: VecDeque<Packet<Reply>>,
    identity: Option<Identity>,
    /// A reset or reopen happened: identify and home before the next motion.
    needs_init: bool,
    resets_seen: u32,
    tolerance_counts: i32,
    /// The position last read or verified, counts, while nothing can have moved the axis since:
    /// cleared by a reset, a reopen and the start of every move. It saves a status round trip
    /// per move (docs/design/acquisition-timing.md).
    known_position: Option<i32>,
    /// Velocity and acceleration set by the user, counts/s and counts/s^2: applied again after
    /// every reset (the controller boots with its defaults).
    motion: Option<(u32, u32)>,
    /// Trigger pulses received and not yet taken, with the seq of the arming command.
    triggers: VecDeque<(u8, TriggerPulse)>,
    /// The seq of the `Spin` in progress (its MotionDone ends the spin).
    spin_seq: Option<u8>,
    /// The seq of the trigger's arming command (its pulses carry it).
    trigger_seq: Option<u8>,
}

fn map_nack(link: &Link, code: ErrorCode, what: &str) -> DeviceError {
    let kind = match code {
        ErrorCode::Busy => ErrorKind::Busy,
        ErrorCode::OutOfRange | ErrorCode::Unsupported => ErrorKind::OutOfRange,
        ErrorCode::Stalled => ErrorKind::Stalled,
        ErrorCode::UnknownCommand | ErrorCode::BadLength => ErrorKind::Protocol,
        ErrorCode::NotHomed | ErrorCode::OverTemperature | ErrorCode::Unknown(_) => {
            ErrorKind::Other
        }
    };
    link.error(kind, format!("{what} refused: {code:?}"))
}

/// The protocol version and identity in an Identify reply.
fn parse_identity(link: &Link, reply: Reply) -> Result<(u8, Identity), DeviceError> {
    match reply {
        Reply::Identity {
            protocol_version,
            firmware,
            device,
            counts_per_turn,
            slots,
            serial,
        } => Ok((
            protocol_version,
            Identity {
                firmware,
                device,
                counts_per_turn,
                slots,
                serial,
            },
        )),
        other => Err(link.error(
            ErrorKind::Protocol,
            format!("expected an identity, got {other:?}"),
        )),
    }
}

impl NativeSession {
    /// Opens the port, identifies the controller (which must be a `kind`, speaking our protocol
    /// version) and homes it.
    pub async fn connect(
        connector: Box<dyn Connector>,
        kind: DeviceKind,
        policy: Policy,
    ) -> Result<Self, DeviceError> {
        let mut s = NativeSession {
            link: Link::new(connector),
            policy,
            kind,
            seq: 0,
            decoder: Decoder::new(),
            packets: VecDeque::new(),
            identity: None,
            needs_init: true,
            resets_seen: 0,
            tolerance_counts: 5,
            known_position: None,
            motion: None,
            triggers: VecDeque::new(),
            spin_seq: None,
            trigger_seq: None,
        };
        s.ensure_ready().await?;
        Ok(s)
    }

    /// The controller's identity.
    pub fn identity(&self) -> Option<Identity> {
        self.identity
    }

    /// Resets (boot notices) seen since connecting.
    pub fn resets_seen(&self) -> u32 {
        self.resets_seen
    }

    /// How many times the port has been opened.
    pub fn opens(&self) -> u32 {
        self.link.opens()
    }

    /// A reset or reopen happened (or is wanted): identify and home before the next motion, and
    /// forget the position.
    fn lose_state(&mut self) {
        self.needs_init = true;
        self.known_position = None;
    }

    /// The axis position, counts: the one last read or verified if nothing can have moved the
    /// axis since, otherwise a status query (kept if the axis is at rest).
    async fn position_counts(&mut self) -> Result<i32, DeviceError> {
        if let (Some(p), false) = (self.known_position, self.needs_init) {
            return Ok(p);
        }
        let s = self.status().await?;
        if !s.flags.has(StatusFlags::MOVING) && !self.needs_init {
            self.known_position = Some(s.position_counts);
        }
        Ok(s.position_counts)
    }

    fn decode_buffer(&mut self) {
        let bytes = std::mem::take(self.link.buffer());
        for b in bytes {
            match self.decoder.feed(b) {
                Some(Ok(p)) => {
                    if let Reply::Boot { reason } = p.message {
                        // A power-on reset is what opening the port does (DTR); anything else
                        // is news.
                        if reason == polar_firmware_protocol::BootReason::PowerOn {
                            tracing::info!(port = %self.link.name(), ?reason, "controller reset");
                        } else {
                            tracing::warn!(port = %self.link.name(), ?reason, "controller reset");
                        }
                        self.resets_seen += 1;
                        self.lose_state();
                    }
                    if let Reply::Trigger {
                        index,
                        position_counts,
                        time_us,
                    } = p.message
                    {
                        // Events, not replies: kept apart so a request in flight does not
                        // discard them as stale.
                        let counts_per_turn = self.identity.map_or(1, |i| i.counts_per_turn);
                        self.triggers.push_back((
                            p.seq,
                            TriggerPulse {
                                index,
                                counts: i64::from(position_counts),
                                angle_rad: f64::from(position_counts)
                                    / f64::from(counts_per_turn.max(1))
                                    * TURN_RAD,
                                device_time_us: time_us,
                            },
                        ));
                        continue;
                    }
                    self.packets.push_back(p);
                }
                Some(Err(e)) => {
                    tracing::debug!(port = %self.link.name(), "skipped a bad frame: {e}")
                }
                None => {}
            }
        }
    }

    async fn next_packet(
        &mut self,
        deadline: Instant,
        what: &str,
    ) -> Result<Packet<Reply>, DeviceError> {
        loop {
            if let Some(p) = self.packets.pop_front() {
                return Ok(p);
            }
            self.link.fill(deadline, what).await?;
            self.decode_buffer();
        }
    }

    fn reset_error(&self) -> DeviceError {
        self.link.error(
            ErrorKind::Protocol,
            "the controller reset during the request",
        )
    }

    /// One request and its reply (matched by sequence number), within the query timeout.
    async fn exchange(&mut self, command: Command) -> Result<(u8, Reply), DeviceError> {
        self.seq = next_seq(self.seq);
        let seq = self.seq;
        self.link
            .write(&encode_vec(seq, &command), self.policy.query_timeout)
            .await?;
        let deadline = Instant::now() + self.policy.query_timeout;
        loop {
            let p = self.next_packet(deadline, "reply").await?;
            match p.message {
                Reply::Boot { .. } => return Err(self.reset_error()),
                Reply::MotionDone { .. } => {}
                reply if p.seq == seq => return Ok((seq, reply)),
                _ => {} // a late or duplicated reply to an earlier request
            }
        }
    }

    /// An idempotent query, retried.
    async fn query(&mut self, command: Command) -> Result<Reply, DeviceError> {
        let mut last = None;
        for k in 0..self.policy.attempts.max(1) {
            self.policy.pause_before(k).await;
            match self.exchange(command).await {
                Ok((_, r)) => return Ok(r),
                Err(e) if matches!(e.kind(), ErrorKind::Timeout | ErrorKind::Protocol) => {
                    last = Some(e)
                }
                Err(e) => return Err(e),
            }
        }
        Err(last.unwrap_or_else(|| self.link.error(ErrorKind::Timeout, "no attempt made")))
    }

    async fn status(&mut self) -> Result<Status, DeviceError> {
        match self.query(Command::GetStatus).await? {
            Reply::Status {
                position_counts,
                flags,
                slot,
            } => Ok(Status {
                position_counts,
                flags,
                slot,
            }),
            Reply::Nack { code } => Err(map_nack(&self.link, code, "status")),
            other => Err(self.link.error(
                ErrorKind::Protocol,
                format!("expected a status, got {other:?}"),
            )),
        }
    }

    /// Waits for the MotionDone of request `seq`.
    async fn wait_done(&mut self, seq: u8, timeout: Duration) -> Result<i32, DeviceError> {
        let deadline = Instant::now() + timeout;
        loop {
            let p = self.next_packet(deadline, "motion-done event").await?;
            match p.message {
                Reply::Boot { .. } => return Err(self.reset_error()),
                Reply::MotionDone { position_counts } if p.seq == seq => {
                    return Ok(position_counts)
                }
                _ => {}
            }
        }
    }

    /// Waits for the MotionDone of request `seq`, asking for the status every second
    /// meanwhile: a lost event then costs at most a second, not the whole move timeout.
    /// Returns the position the MotionDone reports, or `None` if the status found the axis at
    /// rest first (the event was lost).
    async fn wait_done_or_idle(
        &mut self,
        seq: u8,
        timeout: Duration,
    ) -> Result<Option<i32>, DeviceError> {
        let deadline = Instant::now() + timeout;
        loop {
            let now = Instant::now();
            let slice = (deadline.saturating_duration_since(now)).min(Duration::from_secs(1));
            match self.wait_done(seq, slice).await {
                Ok(p) => return Ok(Some(p)),
                Err(e) if e.kind() == ErrorKind::Timeout => {
                    if Instant::now() >= deadline {
                        return Err(e);
                    }
                    match self.status().await {
                        Ok(s) if !s.flags.has(StatusFlags::MOVING) => return Ok(None),
                        Ok(_) => {}
                        Err(e) if e.kind() == ErrorKind::Timeout => {}
                        Err(e) => return Err(e),
                    }
                }
                Err(e) => return Err(e),
            }
        }
    }

    /// Polls the status until the axis stops (or the move timeout passes).
    async fn wait_idle(&mut self) -> Result<Status, DeviceError> {
        let deadline = Instant::now() + self.policy.move_timeout;
        loop {
            let s = self.status().await?;
            if !s.flags.has(StatusFlags::MOVING) {
                return Ok(s);
            }
            if Instant::now() >= deadline {
                return Err(self.link.error(
                    ErrorKind::Timeout,
                    format!("still moving after {:?}", self.policy.move_timeout),
                ));
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    async fn home_once(&mut self) -> Result<(), DeviceError> {
        let (seq, reply) = self.exchange(Command::Home).await?;
        match reply {
            Reply::Ack => {}
            Reply::Nack { code } => return Err(map_nack(&self.link, code, "home")),
            other => {
                return Err(self.link.error(
                    ErrorKind::Protocol,
                    format!("expected an ack to home, got {other:?}"),
                ))
            }
        }
        let timeout = self.policy.home_timeout;
        self.wait_done(seq, timeout).await?;
        let s = self.status().await?;
        if s.flags.has(StatusFlags::HOMED) {
            if !s.flags.has(StatusFlags::MOVING) {
                self.known_position = Some(s.position_counts);
            }
            Ok(())
        } else {
            Err(self
                .link
                .error(ErrorKind::Stalled, "homing ended without the homed flag"))
        }
    }

    /// Opens the port if it is closed, and after a reset or reopen identifies and homes.
    async fn ensure_ready(&mut self) -> Result<(), DeviceError> {
        if !self.link.is_open() {
            self.link.open(self.policy.open_timeout).await?;
            self.decoder.clear();
            self.packets.clear();
            // The controller resets when the port opens (DTR) and announces it; wait for the
            // notice so that it is not taken for a reset later.
            let deadline = Instant::now() + self.policy.query_timeout;
            loop {
                match self.next_packet(deadline, "boot notice").await {
                    Ok(Packet {
                        message: Reply::Boot { .. },
                        ..
                    }) => break,
                    Ok(_) => {}
                    Err(e) if e.kind() == ErrorKind::Timeout => break,
                    Err(e) => return Err(e),
                }
            }
            self.lose_state();
        }
        let policy = self.policy;
        policy.retry_init(self).await
    }

    async fn init(&mut self) -> Result<(), DeviceError> {
        let reply = self.query(Command::Identify).await?;
        let (protocol_version, identity) = parse_identity(&self.link, reply)?;
        if protocol_version != PROTOCOL_VERSION {
            return Err(self.link.error(
                ErrorKind::Other,
                format!(
                    "the controller speaks protocol version {protocol_version}; this driver speaks {PROTOCOL_VERSION}"
                ),
            ));
        }
        let Identity {
            device,
            counts_per_turn,
            slots,
            ..
        } = identity;
        if device != self.kind {
            return Err(self.link.error(
                ErrorKind::Other,
                format!("the controller is a {device:?}, not a {:?}", self.kind),
            ));
        }
        if counts_per_turn == 0 || (device == DeviceKind::FilterWheel && slots == 0) {
            return Err(self.link.error(
                ErrorKind::Protocol,
                format!(
                    "identity out of range: counts_per_turn = {counts_per_turn}, slots = {slots} (both must be > 0)"
                ),
            ));
        }
        self.identity = Some(identity);
        if let Some(motion) = self.motion {
            self.apply_motion(motion).await?;
        }
        tracing::info!(port = %self.link.name(), ?identity, "identified; homing");
        self.home_once().await
    }

    async fn apply_motion(
        &mut self,
        (velocity, acceleration): (u32, u32),
    ) -> Result<(), DeviceError> {
        let command = Command::SetMotion {
            velocity_counts_per_s: velocity,
            acceleration_counts_per_s2: acceleration,
        };
        match self.query(command).await? {
            Reply::Ack => Ok(()),
            Reply::Nack { code } => Err(map_nack(&self.link, code, "set motion")),
            other => Err(self.link.error(
                ErrorKind::Protocol,
                format!("expected an ack to set motion, got {other:?}"),
            )),
        }
    }

    /// Starts or changes velocity mode (counts per second, signed).
    pub async fn spin(&mut self, velocity_counts_per_s: i32) -> Result<(), DeviceError> {
        self.ensure_ready().await?;
        let command = Command::Spin {
            velocity_counts_per_s,
        };
        let (seq, reply) = self.exchange(command).await?;
        match reply {
            Reply::Ack => {
                self.spin_seq = Some(seq);
                self.known_position = None;
                Ok(())
            }
            Reply::Nack { code } => Err(map_nack(&self.link, code, "spin")),
            other => Err(self.link.error(
                ErrorKind::Protocol,
                format!("expected an ack to spin, got {other:?}"),
            )),
        }
    }

    /// Arms the position-compare trigger (counts); drops pulses of earlier armings.
    pub async fn arm_trigger(
        &mut self,
        first_counts: i32,
        interval_counts: i32,
        pulses: u32,
    ) -> Result<(), DeviceError> {
        self.ensure_ready().await?;
        let command = Command::SetTrigger {
            first_counts,
            interval_counts,
            pulses,
        };
        let (seq, reply) = self.exchange(command).await?;
        match reply {
            Reply::Ack => {
                self.triggers.retain(|(s, _)| *s == seq);
                self.trigger_seq = Some(seq);
                Ok(())
            }
            Reply::Nack { code } => Err(map_nack(&self.link, code, "set trigger")),
            other => Err(self.link.error(
                ErrorKind::Protocol,
                format!("expected an ack to set trigger, got {other:?}"),
            )),
        }
    }

    /// The next pulse of the current arming, within `timeout`.
    pub async fn next_trigger(&mut self, timeout: Duration) -> Result<TriggerPulse, DeviceError> {
        let deadline = Instant::now() + timeout;
        loop {
            while let Some((seq, pulse)) = self.triggers.pop_front() {
                if Some(seq) == self.trigger_seq {
                    return Ok(pulse);
                }
            }
            if self.needs_init {
                return Err(self.reset_error());
            }
            self.link.fill(deadline, "trigger pulse").await?;
            self.decode_buffer();
        }
    }

    /// Stops velocity mode; returns the position (counts) of the MotionDone that ends it.
    pub async fn stop_spin(&mut self) -> Result<i32, DeviceError> {
        let Some(spin_seq) = self.spin_seq else {
            return Err(self
                .link
                .error(ErrorKind::Other, "stop spin: the stage is not spinning"));
        };
        match self.query(Command::Stop).await? {
            Reply::Ack => {}
            Reply::Nack { code } => return Err(map_nack(&self.link, code, "stop")),
            other => {
                return Err(self.link.error(
                    ErrorKind::Protocol,
                    format!("expected an ack to stop, got {other:?}"),
                ))
            }
        }
        let timeout = self.policy.move_timeout;
        let position = self.wait_done(spin_seq, timeout).await?;
        self.spin_seq = None;
        self.known_position = Some(position);
        Ok(position)
    }

    /// Sets the cruise velocity and acceleration (kept and applied again after a reset).
    pub async fn set_motion(
        &mut self,
        velocity_counts_per_s: u32,
        acceleration_counts_per_s2: u32,
    ) -> Result<(), DeviceError> {
        self.ensure_ready().await?;
        let motion = (velocity_counts_per_s, acceleration_counts_per_s2);
        self.apply_motion(motion).await?;
        self.motion = Some(motion);
        Ok(())
    }

    /// Moves and checks the result (by the MotionDone's position, or by reading the position or
    /// slot back); repeats on a lost reply, a refusal as busy, a reset or a stall, up to the
    /// policy's attempts. `command` is built for each attempt from the position then (a reset
    /// between attempts moves the datum); rotators get `Some(counts)`, wheels `None`.
    async fn move_verified(
        &mut self,
        command: impl Fn(Option<i32>) -> Command,
    ) -> Result<Status, DeviceError> {
        let mut last = None;
        for k in 0..self.policy.attempts.max(1) {
            self.policy.pause_before(k).await;
            self.ensure_ready().await?;
            let current = match self.kind {
                DeviceKind::Rotator => Some(self.position_counts().await?),
                _ => None,
            };
            let command = command(current);
            match self.move_once(command).await {
                Ok(s) => return Ok(s),
                Err(e) if retryable(&e) => {
                    tracing::warn!(port = %self.link.name(), "move attempt {} failed: {e}", k + 1);
                    last = Some(e);
                }
                Err(e) => return Err(e),
            }
        }
        Err(last.unwrap_or_else(|| self.link.error(ErrorKind::Other, "no attempt made")))
    }

    async fn move_once(&mut self, command: Command) -> Result<Status, DeviceError> {
        self.known_position = None;
        let mut done_at = None;
        match self.exchange(command).await {
            Ok((seq, Reply::Ack)) => {
                let timeout = self.policy.move_timeout;
                match self.wait_done_or_idle(seq, timeout).await {
                    Ok(p) => done_at = p,
                    // Judged by the readback below.
                    Err(e) if e.kind() == ErrorKind::Timeout => {}
                    Err(e) => return Err(e),
                }
            }
            Ok((_, Reply::Nack { code })) => {
                if code == ErrorCode::NotHomed {
                    self.lose_state();
                }
                if code == ErrorCode::Busy {
                    // Possibly our own earlier attempt still moving: let it end first.
                    self.wait_idle().await?;
                }
                return Err(map_nack(&self.link, code, "move"));
            }
            Ok((_, other)) => {
                return Err(self.link.error(
                    ErrorKind::Protocol,
                    format!("expected an ack to the move, got {other:?}"),
                ))
            }
            // The command or its ack was lost: the move may be running. Judge by readback.
            Err(e) if e.kind() == ErrorKind::Timeout => {}
            Err(e) => return Err(e),
        }
        if self.needs_init {
            return Err(self.reset_error());
        }
        // A MotionDone that reports the target settles an absolute move: the controller sends
        // it once the axis is at rest, so a status readback would only repeat it. Anything
        // else (a lost event, a short stop, a slot change) is judged by the readback.
        if let (Some(p), Command::MoveAbsolute { position_counts }) = (done_at, command) {
            if p.wrapping_sub(position_counts).abs() <= self.tolerance_counts {
                self.known_position = Some(p);
                return Ok(Status {
                    position_counts: p,
                    flags: StatusFlags(StatusFlags::HOMED),
                    slot: 0xff,
                });
            }
        }
        let s = self.wait_idle().await?;
        if self.needs_init {
            return Err(self.reset_error());
        }
        let reached = match command {
            Command::MoveAbsolute { position_counts } => {
                (s.position_counts.wrapping_sub(position_counts)).abs() <= self.tolerance_counts
            }
            Command::SelectSlot { slot } => s.slot == slot,
            _ => true,
        };
        if reached {
            self.known_position = Some(s.position_counts);
            Ok(s)
        } else {
            let stalled = if s.flags.has(StatusFlags::STALLED) {
                " (stall reported)"
            } else {
                ""
            };
            Err(self.link.error(
                ErrorKind::Stalled,
                format!(
                    "{command:?} ended at {} counts, slot {}{stalled}",
                    s.position_counts, s.slot
                ),
            ))
        }
    }
}

impl Initialise for NativeSession {
    fn needs_init(&self) -> bool {
        self.needs_init
    }

    /// Clears the need first: `init` sets it again if it sees the controller reset; a failed
    /// attempt forgets the state it may have left half set.
    async fn init_attempt(&mut self) -> Result<(), DeviceError> {
        self.needs_init = false;
        let done = self.init().await;
        if done.is_err() {
            self.lose_state();
        }
        done
    }

    fn init_failed(&self) -> DeviceError {
        self.link
            .error(ErrorKind::Other, "could not initialise the controller")
    }
}

/// What [`probe`] finds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Probe {
    /// The identity.
    pub identity: Identity,
    /// The position, counts (meaningful once homed).
    pub position_counts: i32,
    /// Whether the axis has a datum.
    pub homed: bool,
    /// The slot (wheels at rest on one).
    pub slot: Option<u8>,
}

/// Opens the port and asks the controller what it is and where it is, without moving it.
pub async fn probe(connector: Box<dyn Connector>, policy: Policy) -> Result<Probe, DeviceError> {
    let mut s = NativeSession {
        link: Link::new(connector),
        policy,
        kind: DeviceKind::Unknown(0),
        seq: 0,
        decoder: Decoder::new(),
        packets: VecDeque::new(),
        identity: None,
        needs_init: false,
        resets_seen: 0,
        tolerance_counts: 5,
        known_position: None,
        motion: None,
        triggers: VecDeque::new(),
        spin_seq: None,
        trigger_seq: None,
    };
    s.link.open(policy.open_timeout).await?;
    let reply = s.query(Command::Identify).await?;
    let (_, identity) = parse_identity(&s.link, reply)?;
    let status = s.status().await?;
    Ok(Probe {
        identity,
        position_counts: status.position_counts,
        homed: status.flags.has(StatusFlags::HOMED),
        slot: (status.slot != 0xff).then_some(status.slot),
    })
}

/// Our firmware's rotation stage.
pub struct NativeRotator {
    session: NativeSession,
    info: RotatorInfo,
}

impl NativeRotator {
    /// Connects, identifies and homes.
    pub async fn connect(
        connector: Box<dyn Connector>,
        policy: Policy,
    ) -> Result<Self, DeviceError> {
        let session = NativeSession::connect(connector, DeviceKind::Rotator, policy).await?;
        let identity = session.identity().ok_or_else(|| {
            session
                .link
                .error(ErrorKind::Other, "connected without an identity")
        })?;
        let counts_per_turn = identity.counts_per_turn;
        Ok(NativeRotator {
            info: RotatorInfo {
                model: format!(
                    "native rotator serial {:08x} firmware {}.{}.{}",
                    identity.serial,
                    identity.firmware[0],
                    identity.firmware[1],
                    identity.firmware[2]
                ),
                counts_per_turn,
                tolerance_rad: session.tolerance_counts as f64 / counts_per_turn as f64 * TURN_RAD,
            },
            session,
        })
    }

    /// The position as the controller reports it now, radians: always a status round trip,
    /// unlike [`Rotator::position_rad`], which knows the position between moves.
    pub async fn read_position_rad(&mut self) -> Result<f64, DeviceError> {
        self.session.ensure_ready().await?;
        let p = self.session.status().await?.position_counts;
        Ok(self.angle(p))
    }

    /// The session (identity, resets seen, opens).
    pub fn session(&self) -> &NativeSession {
        &self.session
    }

    /// Velocity mode: turns continuously at `velocity_rad_per_s` (signed) until
    /// [`NativeRotator::stop_spin`]; a second call changes the speed without stopping. Errors
    /// (OutOfRange) name the velocity and its allowed range; a firmware without velocity mode
    /// answers Unsupported.
    pub async fn spin(&mut self, velocity_rad_per_s: f64) -> Result<(), DeviceError> {
        let per_rad = f64::from(self.info.counts_per_turn) / TURN_RAD;
        let counts = (velocity_rad_per_s * per_rad).round();
        if !(counts.is_finite() && counts != 0.0 && counts.abs() <= f64::from(i32::MAX)) {
            return Err(self.session.link.error(
                ErrorKind::OutOfRange,
                format!(
                    "spin velocity {velocity_rad_per_s} rad/s is out of range: allowed a \
                     non-zero speed of at least one count per second ({:.3e} rad/s)",
                    1.0 / per_rad
                ),
            ));
        }
        self.session.spin(counts as i32).await
    }

    /// Arms the position-compare trigger: `pulses` pulses, at `first_rad` (unwrapped, from the
    /// datum) and then every `interval_rad` (signed: the direction of motion that fires).
    /// Pulses queued from an earlier arming are dropped.
    pub async fn arm_trigger(
        &mut self,
        first_rad: f64,
        interval_rad: f64,
        pulses: u32,
    ) -> Result<(), DeviceError> {
        let per_rad = f64::from(self.info.counts_per_turn) / TURN_RAD;
        let first = (first_rad * per_rad).round();
        let interval = (interval_rad * per_rad).round();
        let fits = |x: f64| x.is_finite() && x.abs() <= f64::from(i32::MAX);
        if !(fits(first) && fits(interval) && (interval != 0.0 || pulses == 0)) {
            return Err(self.session.link.error(
                ErrorKind::OutOfRange,
                format!(
                    "trigger first {first_rad} rad, interval {interval_rad} rad are out of \
                     range: allowed an interval of at least one count ({:.3e} rad) and \
                     positions within +-2^31 counts",
                    1.0 / per_rad
                ),
            ));
        }
        self.session
            .arm_trigger(first as i32, interval as i32, pulses)
            .await
    }

    /// The next trigger pulse of the current arming, waiting up to `timeout`.
    pub async fn next_trigger(&mut self, timeout: Duration) -> Result<TriggerPulse, DeviceError> {
        self.session.next_trigger(timeout).await
    }

    /// Ends velocity mode: ramps down and returns where the stage stopped, radians in
    /// `[0, 2 pi)`.
    pub async fn stop_spin(&mut self) -> Result<f64, DeviceError> {
        let counts = self.session.stop_spin().await?;
        Ok(self.angle(counts))
    }

    fn angle(&self, counts: i32) -> f64 {
        angle_from_counts(i64::from(counts), self.info.counts_per_turn)
    }
}

impl Rotator for NativeRotator {
    fn info(&self) -> &RotatorInfo {
        &self.info
    }

    async fn home(&mut self) -> Result<(), DeviceError> {
        self.session.lose_state();
        self.session.ensure_ready().await
    }

    async fn move_to(&mut self, angle_rad: f64) -> Result<f64, DeviceError> {
        if !angle_rad.is_finite() {
            return Err(self.session.link.error(
                ErrorKind::OutOfRange,
                format!("angle_rad = {angle_rad} is not a finite angle"),
            ));
        }
        let cpt = self.info.counts_per_turn;
        let s = self
            .session
            .move_verified(|current| Command::MoveAbsolute {
                position_counts: counts_toward(current.unwrap_or(0), angle_rad, cpt),
            })
            .await?;
        Ok(self.angle(s.position_counts))
    }

    /// The controller's position count as an angle. The count changes only by our moves (it is
    /// not an encoder), so after a verified move it is known without asking; after a reset,
    /// reopen or failed move it is read.
    async fn position_rad(&mut self) -> Result<f64, DeviceError> {
        self.session.ensure_ready().await?;
        let p = self.session.position_counts().await?;
        Ok(self.angle(p))
    }

    fn supports_velocity(&self) -> bool {
        true
    }

    fn continuous_support(&self) -> ContinuousSupport {
        ContinuousSupport::VelocityAndTrigger
    }

    async fn spin(&mut self, rad_per_s: f64) -> Result<(), DeviceError> {
        NativeRotator::spin(self, rad_per_s).await
    }

    async fn stop_spin(&mut self) -> Result<f64, DeviceError> {
        NativeRotator::stop_spin(self).await
    }

    /// A status round trip (the count is the controller's, unwrapped).
    async fn spin_position_rad(&mut self) -> Result<f64, DeviceError> {
        self.session.ensure_ready().await?;
        let p = self.session.status().await?.position_counts;
        Ok(f64::from(p) / f64::from(self.info.counts_per_turn.max(1)) * TURN_RAD)
    }

    /// `GetStatus` and its `Status` frames at the port's baud, 8N1.
    fn spin_read_wire(&self) -> WireTimes {
        let request = encode_vec(0, &Command::GetStatus).len();
        let reply = encode_vec(
            0,
            &Reply::Status {
                position_counts: 0,
                flags: StatusFlags::default(),
                slot: 0,
            },
        )
        .len();
        WireTimes::uart(request, reply, DIALECT.baud, 10)
    }

    async fn arm_trigger(
        &mut self,
        first_rad: f64,
        interval_rad: f64,
        count: u32,
    ) -> Result<(), DeviceError> {
        NativeRotator::arm_trigger(self, first_rad, interval_rad, count).await
    }

    async fn next_trigger(&mut self, timeout: Duration) -> Result<TriggerPulse, DeviceError> {
        NativeRotator::next_trigger(self, timeout).await
    }

    /// Cruise at `rad_per_s` (up to 10 turns/s), accelerating to it in 0.25 s.
    async fn set_velocity(&mut self, rad_per_s: f64) -> Result<(), DeviceError> {
        let max = 10.0 * TURN_RAD;
        if !(rad_per_s > 0.0 && rad_per_s <= max) {
            return Err(self.session.link.error(
                ErrorKind::OutOfRange,
                format!("velocity = {rad_per_s} rad/s is out of range: allowed (0, {max:.1}]"),
            ));
        }
        let cpt = self.info.counts_per_turn as f64;
        let v = (rad_per_s / TURN_RAD * cpt)
            .round()
            .clamp(1.0, u32::MAX as f64 / 4.0) as u32;
        self.session.set_motion(v, v.saturating_mul(4)).await
    }
}

/// Our firmware's filter wheel.
pub struct NativeWheel {
    session: NativeSession,
    labels: Vec<String>,
}

impl NativeWheel {
    /// Connects, identifies and homes; slots are labelled by number unless `labels` names them
    /// (one per slot).
    pub async fn connect(
        connector: Box<dyn Connector>,
        policy: Policy,
        labels: Option<Vec<String>>,
    ) -> Result<Self, DeviceError> {
        let session = NativeSession::connect(connector, DeviceKind::FilterWheel, policy).await?;
        let slots = session.identity().map_or(0, |i| i.slots as usize);
        let labels = match labels {
            Some(l) if l.len() == slots => l,
            Some(l) => {
                return Err(session.link.error(
                    ErrorKind::OutOfRange,
                    format!("{} slot labels given; the wheel has {slots} slots", l.len()),
                ))
            }
            None => (0..slots).map(|s| format!("slot {s}")).collect(),
        };
        Ok(NativeWheel { session, labels })
    }

    /// The session (identity, resets seen, opens).
    pub fn session(&self) -> &NativeSession {
        &self.session
    }
}

impl FilterWheel for NativeWheel {
    fn slots(&self) -> &[String] {
        &self.labels
    }

    async fn select(&mut self, slot: usize) -> Result<usize, DeviceError> {
        if slot >= self.labels.len() {
            return Err(self.session.link.error(
                ErrorKind::OutOfRange,
                format!(
                    "slot = {slot} is out of range: allowed 0..={}",
                    self.labels.len().saturating_sub(1)
                ),
            ));
        }
        let s = self
            .session
            .move_verified(|_| Command::SelectSlot { slot: slot as u8 })
            .await?;
        Ok(s.slot as usize)
    }

    async fn slot(&mut self) -> Result<Option<usize>, DeviceError> {
        self.session.ensure_ready().await?;
        let s = self.session.status().await?;
        Ok((s.slot != 0xff && !s.flags.has(StatusFlags::MOVING)).then_some(s.slot as usize))
    }
}

/// Our firmware (`firmware-protocol/SPEC.md`).
pub const DIALECT: Dialect = Dialect {
    name: "native",
    description: "our firmware (firmware-protocol/SPEC.md): rotation stage or six-slot wheel",
    kinds: &[dialect::DeviceKind::Rotator, dialect::DeviceKind::Wheel],
    models: &["rotator", "wheel"],
    baud: 115_200,
    line: LINE_8N1,
    bus: None,
    policy: default_policy,
    identify: |c, _, policy| {
        Box::pin(async move {
            let p = probe(c, policy).await?;
            let id = p.identity;
            let rotator = id.device == DeviceKind::Rotator;
            Ok(dialect::Identity {
                kind: if rotator {
                    dialect::DeviceKind::Rotator
                } else {
                    dialect::DeviceKind::Wheel
                },
                model: format!("{:?}", id.device),
                serial: format!("{:08x}", id.serial),
                firmware: format!("{}.{}.{}", id.firmware[0], id.firmware[1], id.firmware[2]),
                counts_per_turn: rotator.then_some(id.counts_per_turn),
                slots: (!rotator).then_some(usize::from(id.slots)),
                homed: Some(p.homed),
                position: if rotator {
                    let a = angle_from_counts(i64::from(p.position_counts), id.counts_per_turn);
                    Position::Angle {
                        deg: a.to_degrees(),
                    }
                } else {
                    Position::Slot(p.slot.map(usize::from))
                },
            })
        })
    },
    rotator: Some(|c, _, policy| {
        Box::pin(async move { Ok(AnyRotator::new(NativeRotator::connect(c, policy).await?)) })
    }),
    wheel: Some(|c, _, policy| {
        Box::pin(async move { Ok(AnyWheel::new(NativeWheel::connect(c, policy, None).await?)) })
    }),
};
