//! Thorlabs FW102C (6 positions) and FW212C (12 positions) filter wheels, written from
//! `docs/DEVICES.md` section 1.2 (ISIS IBEX manual, pylablib, the Simond and
//! Pazdzior drivers).
//!
//! * Commands are ASCII lines ending `\r`. The wheel echoes the command, sends the answer line
//!   of a query, then the prompt `>`; for `pos=n` the prompt comes when the move has ended.
//! * Input is discarded before each command, and nothing counts until the echo of *this*
//!   command has been seen: line noise, stale prompts and late answers before it are skipped.
//!   A corrupted echo or answer makes the exchange fail and be repeated (all commands used
//!   here are idempotent).
//! * A line containing `CMD_` or `error` is the wheel refusing the command.
//! * Every `pos=` is verified with `pos?`. Slots are 0-based in this API, 1-based on the wire.
//! * `respect_bound` (pylablib, Pazdzior) splits a move of half the wheel or more into two, so
//!   the wheel never jumps straight across the first/last boundary; off by default.

use crate::any::AnyWheel;
use crate::dialect::{wheel_identity, DeviceKind, Dialect, LINE_8N1};
use crate::link::{Connector, Link, Policy};
use polar_hal::{DeviceError, ErrorKind, FilterWheel};
use std::time::Duration;
use tokio::time::Instant;

/// The default policy (115200 baud; a move takes up to a few seconds).
pub fn default_policy() -> Policy {
    Policy {
        open_timeout: Duration::from_secs(2),
        query_timeout: Duration::from_millis(500),
        move_timeout: Duration::from_secs(6),
        home_timeout: Duration::from_secs(6),
        attempts: 4,
        backoff: Duration::from_millis(50),
    }
}

/// An FW102C or FW212C.
pub struct Fw102c {
    link: Link,
    policy: Policy,
    identity: String,
    labels: Vec<String>,
    /// Split long moves in two (see the module docs).
    pub respect_bound: bool,
    last_slot: Option<usize>,
    resets_seen: u32,
}

/// What an exchange returned: the lines between the echo and the prompt.
type Answer = Vec<String>;

impl Fw102c {
    /// Opens the port, checks the identity (`*idn?` must name FW102C or FW212C) and reads the
    /// number of positions (`pcount?`).
    pub async fn connect(
        connector: Box<dyn Connector>,
        policy: Policy,
    ) -> Result<Self, DeviceError> {
        let mut wheel = Fw102c {
            link: Link::new(connector),
            policy,
            identity: String::new(),
            labels: Vec::new(),
            respect_bound: false,
            last_slot: None,
            resets_seen: 0,
        };
        wheel.ensure_ready().await?;
        Ok(wheel)
    }

    /// The `*idn?` answer.
    pub fn identity(&self) -> &str {
        &self.identity
    }

    /// How many times the port has been opened.
    pub fn opens(&self) -> u32 {
        self.link.opens()
    }

    /// Times the wheel was found off the slot it was left on (a reset or a hand turn).
    pub fn resets_seen(&self) -> u32 {
        self.resets_seen
    }

    async fn ensure_ready(&mut self) -> Result<(), DeviceError> {
        if self.link.is_open() && !self.labels.is_empty() {
            return Ok(());
        }
        if !self.link.is_open() {
            self.link.open(self.policy.open_timeout).await?;
        }
        let idn = self.query("*idn?").await?;
        if !(idn.contains("FW102C") || idn.contains("FW212C")) {
            return Err(self.link.error(
                ErrorKind::Other,
                format!("`*idn?` answered {idn:?}: not an FW102C/FW212C"),
            ));
        }
        let pcount = self.query("pcount?").await?;
        let slots: usize = match pcount.trim().parse() {
            Ok(n @ (6 | 12)) => n,
            _ => {
                return Err(self.link.error(
                    ErrorKind::Protocol,
                    format!("`pcount?` answered {pcount:?}: allowed 6 or 12"),
                ))
            }
        };
        tracing::info!(port = %self.link.name(), %idn, slots, "identified");
        self.identity = idn;
        self.labels = (0..slots).map(|s| format!("slot {s}")).collect();
        Ok(())
    }

    /// Finds `echo` in the buffer and returns the lines after it up to the prompt, if complete.
    fn scan(&mut self, echo: &[u8]) -> Option<Answer> {
        let buf = self.link.buffer();
        let start = buf.windows(echo.len()).position(|w| w == echo)?;
        let after = start + echo.len();
        let prompt = buf[after..].iter().position(|&b| b == b'>')? + after;
        let text = String::from_utf8_lossy(&buf[after..prompt]).into_owned();
        buf.drain(..=prompt);
        Some(
            text.split(['\r', '\n'])
                .map(str::trim)
                .filter(|l| !l.is_empty())
                .map(str::to_string)
                .collect(),
        )
    }

    /// One command: discard input, send, wait for the echo, the answer lines and the prompt.
    async fn exchange(&mut self, command: &str, timeout: Duration) -> Result<Answer, DeviceError> {
        self.link.discard_input().await?;
        let line = format!("{command}\r");
        self.link
            .write(line.as_bytes(), self.policy.query_timeout)
            .await?;
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(answer) = self.scan(line.as_bytes()) {
                if let Some(e) = answer
                    .iter()
                    .find(|l| l.contains("CMD_") || l.to_ascii_lowercase().contains("error"))
                {
                    let kind = if e.contains("CMD_ARG_INVALID") {
                        ErrorKind::OutOfRange
                    } else {
                        ErrorKind::Protocol
                    };
                    return Err(self.link.error(kind, format!("`{command}` refused: {e}")));
                }
                return Ok(answer);
            }
            self.link
                .fill(deadline, &format!("echo and prompt of `{command}`"))
                .await?;
        }
    }

    /// A query's single answer line, retried.
    async fn query(&mut self, command: &str) -> Result<String, DeviceError> {
        let mut last = None;
        for k in 0..self.policy.attempts.max(1) {
            self.policy.pause_before(k).await;
            match self.exchange(command, self.policy.query_timeout).await {
                Ok(answer) if answer.len() == 1 => return Ok(answer[0].clone()),
                Ok(answer) => {
                    last = Some(self.link.error(
                        ErrorKind::Protocol,
                        format!("`{command}` answered {answer:?}: expected one line"),
                    ))
                }
                Err(e) if matches!(e.kind(), ErrorKind::Timeout | ErrorKind::Protocol) => {
                    last = Some(e)
                }
                Err(e) => return Err(e),
            }
        }
        Err(last.unwrap_or_else(|| self.link.error(ErrorKind::Timeout, "no attempt made")))
    }

    /// The current slot (0-based).
    async fn position(&mut self) -> Result<usize, DeviceError> {
        let answer = self.query("pos?").await?;
        match answer.trim().parse::<usize>() {
            Ok(n) if (1..=self.labels.len()).contains(&n) => Ok(n - 1),
            _ => Err(self.link.error(
                ErrorKind::Protocol,
                format!(
                    "`pos?` answered {answer:?}: allowed 1..={}",
                    self.labels.len()
                ),
            )),
        }
    }

    async fn go(&mut self, slot: usize) -> Result<(), DeviceError> {
        let command = format!("pos={}", slot + 1);
        match self.exchange(&command, self.policy.move_timeout).await {
            Ok(_) => Ok(()),
            // A lost echo or prompt: judged by `pos?`.
            Err(e) if matches!(e.kind(), ErrorKind::Timeout | ErrorKind::Protocol) => {
                tracing::warn!(port = %self.link.name(), "{command}: {e}; judging by `pos?`");
                Ok(())
            }
            Err(e) => Err(e),
        }
    }

    async fn select_once(&mut self, slot: usize) -> Result<usize, DeviceError> {
        let current = self.position().await?;
        if let Some(last) = self.last_slot {
            if last != current {
                tracing::warn!(port = %self.link.name(), "wheel at slot {current}, left at {last}");
                self.resets_seen += 1;
            }
        }
        let n = self.labels.len();
        let steps = (slot + n - current) % n;
        if self.respect_bound && steps.min(n - steps) * 2 >= n {
            let halfway = (current + steps / 2) % n;
            self.go(halfway).await?;
        }
        self.go(slot).await?;
        let reached = self.position().await?;
        self.last_slot = Some(reached);
        if reached == slot {
            Ok(reached)
        } else {
            Err(self.link.error(
                ErrorKind::Stalled,
                format!("asked for slot {slot}, the wheel is at slot {reached}"),
            ))
        }
    }
}

impl FilterWheel for Fw102c {
    fn slots(&self) -> &[String] {
        &self.labels
    }

    async fn select(&mut self, slot: usize) -> Result<usize, DeviceError> {
        if slot >= self.labels.len() {
            return Err(self.link.error(
                ErrorKind::OutOfRange,
                format!(
                    "slot = {slot} is out of range: allowed 0..={}",
                    self.labels.len().saturating_sub(1)
                ),
            ));
        }
        let mut last = None;
        for k in 0..self.policy.attempts.max(1) {
            self.policy.pause_before(k).await;
            self.ensure_ready().await?;
            match self.select_once(slot).await {
                Ok(s) => return Ok(s),
                Err(e)
                    if matches!(
                        e.kind(),
                        ErrorKind::Timeout | ErrorKind::Protocol | ErrorKind::Stalled
                    ) =>
                {
                    tracing::warn!(port = %self.link.name(), "select attempt {} failed: {e}", k + 1);
                    last = Some(e)
                }
                Err(e) => return Err(e),
            }
        }
        Err(last.unwrap_or_else(|| self.link.error(ErrorKind::Other, "no attempt made")))
    }

    async fn slot(&mut self) -> Result<Option<usize>, DeviceError> {
        self.ensure_ready().await?;
        self.position().await.map(Some)
    }
}

/// Thorlabs FW102C/FW212C filter wheels.
pub const DIALECT: Dialect = Dialect {
    name: "fw102c",
    description: "Thorlabs FW102C/FW212C filter wheels (ASCII, echo and prompt)",
    kinds: &[DeviceKind::Wheel],
    models: &["fw102c", "fw212c"],
    baud: 115_200,
    line: LINE_8N1,
    bus: None,
    policy: default_policy,
    identify: |c, _, policy| {
        Box::pin(async move {
            let w = Fw102c::connect(c, policy).await?;
            let model = w.identity().to_string();
            wheel_identity(w, model).await
        })
    },
    rotator: None,
    wheel: Some(|c, _, policy| {
        Box::pin(async move { Ok(AnyWheel::new(Fw102c::connect(c, policy).await?)) })
    }),
};
