//! Serial-port triggers: the line protocol of `hil/trigger-protocol.md`, a reader thread that
//! owns the port, acknowledgements written back to the rig, modem-status lines as hardware
//! triggers, and the replay of recorded triggers from a ground-truth log.
//!
//! Data flow (live):
//!
//! ```text
//!  serial port ──bytes──▶ reader thread: LineAssembler → parse_line (validated against the
//!      ▲                  campaign's Catalog) ──Incoming──▶ channel ──▶ campaign controller
//!      │                   │  (garbage: NAK at once)                     (applies at the next
//!      └── writer thread ◀─┴──────────── ACK/NAK/EDGE lines ◀──────────── before_frame, acks)
//! ```
//!
//! The controller ([`crate::schedule::CampaignController`]) applies every pending command
//! before the next frame enters the chain, so a change takes effect on a well-defined frame,
//! and acknowledges with that frame's sequence number and stream time. Replies go through a
//! writer thread with a bounded queue: a rig that stops reading never stalls the stream
//! (replies are dropped and counted instead).

use crate::faults::{EffectInfo, ParamKind};
use crossbeam_channel::{Receiver, Sender, TryRecvError, TrySendError, bounded};
use serialport::SerialPort;
use std::io::{Read, Write};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use thiserror::Error;

/// Longest accepted line (bytes, without the terminator) unless configured otherwise.
pub const DEFAULT_MAX_LINE_BYTES: usize = 256;
/// A line whose terminator does not arrive within this time is discarded as partial (ms).
pub const DEFAULT_PARTIAL_TIMEOUT_MS: u64 = 500;
/// How often the reader wakes up to poll modem lines and check timeouts (ms).
pub const DEFAULT_POLL_MS: u64 = 2;
/// Default baud rate.
pub const DEFAULT_BAUD: u32 = 115_200;
/// Replies queued for the writer thread before new ones are dropped.
const REPLY_QUEUE: usize = 256;
/// Items queued from the reader to the controller; the reader blocks when full (backpressure).
const INCOMING_QUEUE: usize = 1024;
/// At most this many bytes of a rejected line are echoed in a NAK or the log.
const ECHO_BYTES: usize = 40;

/// Commands of the protocol, in the order they are documented.
pub const COMMANDS: &[&str] = &["START", "STOP", "SET", "ARM", "DISARM", "MARK", "PING"];

/// Errors opening or reading trigger inputs.
#[derive(Debug, Error)]
pub enum TriggerError {
    #[error("serial port {port}: cannot open at {baud} baud: {source}")]
    Open { port: String, baud: u32, source: serialport::Error },
    #[error("serial port {port}: {what}: {source}")]
    Port { port: String, what: &'static str, source: serialport::Error },
    #[error("cannot start the {0} thread: {1}")]
    Thread(&'static str, std::io::Error),
    #[error("{file}: cannot read the trigger log: {source}")]
    ReplayIo { file: String, source: std::io::Error },
    #[error("{file}:{line}: {message}")]
    ReplayBad { file: String, line: usize, message: String },
}

// ---------------------------------------------------------------------------------------------
// Commands and their validation

/// What a `SET` changes.
#[derive(Debug, Clone, PartialEq)]
pub enum SetTarget {
    /// A parameter (index into the effect's `info.params`) to a numeric value (choices: index).
    Param { param: usize, value: f64 },
    /// Switch the effect on or off.
    Enabled(bool),
}

/// A validated command.
#[derive(Debug, Clone, PartialEq)]
pub enum Command {
    /// Start the events with this name or gated by this trigger name.
    Start(String),
    /// Stop them.
    Stop(String),
    /// Change an effect's baseline (config index `index`).
    Set {
        index: usize,
        target: SetTarget,
    },
    Arm,
    Disarm,
    /// A label for the log, aligned with a frame.
    Mark(String),
    Ping,
}

/// What the protocol can name: built from the campaign so commands are checked on arrival.
#[derive(Debug, Clone, Default)]
pub struct Catalog {
    /// Event names and trigger names accepted by START/STOP.
    pub names: Vec<String>,
    /// Configured effects in config order: (name, info).
    pub effects: Vec<(String, &'static EffectInfo)>,
}

impl Catalog {
    fn effect_ref(&self, word: &str) -> Result<usize, String> {
        let (name, idx) = match word.split_once('#') {
            Some((n, i)) => match i.parse::<usize>() {
                Ok(i) => (n, Some(i)),
                Err(_) => return Err(format!("bad effect index in '{}'; use <effect>#<index>", echo(word.as_bytes()))),
            },
            None => (word, None),
        };
        let listed =
            || self.effects.iter().enumerate().map(|(i, (n, _))| format!("{n}#{i}")).collect::<Vec<_>>().join(", ");
        let matches: Vec<usize> =
            self.effects.iter().enumerate().filter(|(_, (n, _))| n == name).map(|(i, _)| i).collect();
        match (idx, matches.len()) {
            (_, 0) => Err(format!("unknown effect '{}'; configured: {}", echo(name.as_bytes()), listed())),
            (None, 1) => Ok(matches[0]),
            (None, _) => {
                Err(format!("effect '{name}' is configured {} times; name one as {}", matches.len(), listed()))
            }
            (Some(i), _) if matches.contains(&i) => Ok(i),
            (Some(i), _) => Err(format!("'{name}#{i}' is not configured; configured: {}", listed())),
        }
    }
}

/// Printable, single-line echo of (part of) a rejected input.
pub fn echo(bytes: &[u8]) -> String {
    let mut s = String::new();
    for &b in bytes.iter().take(ECHO_BYTES) {
        if (0x20..0x7f).contains(&b) {
            s.push(b as char);
        } else {
            s.push_str(&format!("\\x{b:02x}"));
        }
    }
    if bytes.len() > ECHO_BYTES {
        s.push_str("...");
    }
    s
}

/// Names in the protocol (events, triggers, marks' words): `[A-Za-z0-9_.-]+`.
pub fn valid_name(s: &str) -> bool {
    !s.is_empty() && s.len() <= 64 && s.bytes().all(|b| b.is_ascii_alphanumeric() || b"_.-".contains(&b))
}

/// Parse a command body (everything after the sequence number) against the catalog.
pub fn parse_command(body: &str, cat: &Catalog) -> Result<Command, String> {
    let mut words = body.split_ascii_whitespace();
    let Some(word) = words.next() else {
        return Err(format!("missing command; accepted: {}", COMMANDS.join(", ")));
    };
    let rest: Vec<&str> = words.collect();
    let verb = word.to_ascii_uppercase();
    let nargs = |n: usize, usage: &str| -> Result<(), String> {
        if rest.len() == n { Ok(()) } else { Err(format!("{verb} takes {n} argument(s): {usage}")) }
    };
    match verb.as_str() {
        "START" | "STOP" => {
            nargs(1, "<seq> START|STOP <event or trigger>")?;
            let name = rest[0];
            if cat.names.iter().any(|n| n == name) {
                Ok(if verb == "START" { Command::Start(name.to_string()) } else { Command::Stop(name.to_string()) })
            } else {
                Err(format!(
                    "unknown event or trigger '{}'; accepted: {}",
                    echo(name.as_bytes()),
                    if cat.names.is_empty() {
                        "(the campaign has no events)".to_string()
                    } else {
                        cat.names.join(", ")
                    }
                ))
            }
        }
        "SET" => {
            nargs(2, "<seq> SET <effect>[#<index>].<param> <value>")?;
            let Some((eff, param)) = rest[0].rsplit_once('.') else {
                return Err(format!("SET needs <effect>.<param>, got '{}'", echo(rest[0].as_bytes())));
            };
            let index = cat.effect_ref(eff)?;
            let (name, info) = &cat.effects[index];
            let value = rest[1];
            if param == "enabled" {
                return match value.to_ascii_lowercase().as_str() {
                    "true" | "1" | "on" => Ok(Command::Set { index, target: SetTarget::Enabled(true) }),
                    "false" | "0" | "off" => Ok(Command::Set { index, target: SetTarget::Enabled(false) }),
                    _ => Err(format!(
                        "{name}.enabled = '{}' is not accepted; accepted: true or false",
                        echo(value.as_bytes())
                    )),
                };
            }
            let Some((pi, spec)) = info.param(param) else {
                return Err(format!(
                    "{name}: unknown parameter '{}'; accepted: enabled, {}",
                    echo(param.as_bytes()),
                    info.params.iter().map(|p| p.name).collect::<Vec<_>>().join(", ")
                ));
            };
            let v = match spec.kind {
                ParamKind::Choice(c) => match c.iter().position(|w| *w == value) {
                    Some(k) => k as f64,
                    None => {
                        return Err(format!(
                            "{name}.{param} = '{}' is not accepted; accepted: {}",
                            echo(value.as_bytes()),
                            spec.range_text()
                        ));
                    }
                },
                ParamKind::Bool => match value.to_ascii_lowercase().as_str() {
                    "true" | "1" => 1.0,
                    "false" | "0" => 0.0,
                    _ => {
                        return Err(format!(
                            "{name}.{param} = '{}' is not accepted; accepted: true or false",
                            echo(value.as_bytes())
                        ));
                    }
                },
                ParamKind::Int | ParamKind::Float => match value.parse::<f64>() {
                    Ok(v) => v,
                    Err(_) => {
                        return Err(format!(
                            "{name}.{param} = '{}' is not a number; accepted: {}",
                            echo(value.as_bytes()),
                            spec.range_text()
                        ));
                    }
                },
            };
            spec.check(info.name, v).map_err(|e| e.to_string())?;
            Ok(Command::Set { index, target: SetTarget::Param { param: pi, value: v } })
        }
        "ARM" => nargs(0, "<seq> ARM").map(|_| Command::Arm),
        "DISARM" => nargs(0, "<seq> DISARM").map(|_| Command::Disarm),
        "PING" => nargs(0, "<seq> PING").map(|_| Command::Ping),
        "MARK" => {
            let label = rest.join(" ");
            if label.is_empty() {
                Err("MARK needs a label: <seq> MARK <label>".into())
            } else if !label.bytes().all(|b| (0x20..0x7f).contains(&b)) {
                Err("MARK label must be printable ASCII".into())
            } else {
                Ok(Command::Mark(label))
            }
        }
        _ => Err(format!("unknown command '{}'; accepted: {}", echo(word.as_bytes()), COMMANDS.join(", "))),
    }
}

impl Command {
    /// Canonical text (without sequence number); [`parse_command`] reads it back to the same
    /// command. Recorded in the ground-truth log and replayed from there.
    pub fn text(&self, cat: &Catalog) -> String {
        match self {
            Command::Start(n) => format!("START {n}"),
            Command::Stop(n) => format!("STOP {n}"),
            Command::Set { index, target } => {
                let (name, info) = match cat.effects.get(*index) {
                    Some((n, i)) => (n.as_str(), Some(*i)),
                    None => ("?", None),
                };
                match target {
                    SetTarget::Enabled(b) => format!("SET {name}#{index}.enabled {b}"),
                    SetTarget::Param { param, value } => {
                        let spec = info.and_then(|i| i.params.get(*param));
                        let pname = spec.map(|s| s.name).unwrap_or("?");
                        let v = match spec.map(|s| s.kind) {
                            Some(ParamKind::Choice(c)) => c.get(*value as usize).copied().unwrap_or("?").to_string(),
                            Some(ParamKind::Bool) => (*value != 0.0).to_string(),
                            _ => format!("{value}"),
                        };
                        format!("SET {name}#{index}.{pname} {v}")
                    }
                }
            }
            Command::Arm => "ARM".into(),
            Command::Disarm => "DISARM".into(),
            Command::Mark(l) => format!("MARK {l}"),
            Command::Ping => "PING".into(),
        }
    }
}

/// Parse one complete line (without terminator): `<seq> <COMMAND> [args]`.
/// Errors carry the sequence number when it could be read.
pub fn parse_line(line: &[u8], cat: &Catalog) -> Result<(u64, Command), (Option<u64>, String)> {
    // The sequence number is read from the raw bytes so even an invalid-UTF-8 line is NAKed
    // with its number.
    let start = line.iter().position(|b| !b.is_ascii_whitespace()).unwrap_or(line.len());
    let digits = line[start..].iter().take_while(|b| b.is_ascii_digit()).count();
    let after = start + digits;
    let seq = if digits > 0 && (after == line.len() || line[after].is_ascii_whitespace()) {
        std::str::from_utf8(&line[start..after]).ok().and_then(|s| s.parse::<u64>().ok())
    } else {
        None
    };
    let text = match std::str::from_utf8(line) {
        Ok(t) => t,
        Err(e) => return Err((seq, format!("invalid UTF-8 at byte {}", e.valid_up_to()))),
    };
    let Some(seq) = seq else {
        return Err((
            None,
            format!("expected '<seq> <COMMAND> [args]' with a decimal sequence number, got '{}'", echo(line)),
        ));
    };
    parse_command(&text[after..], cat).map(|c| (seq, c)).map_err(|e| (Some(seq), e))
}

// ---------------------------------------------------------------------------------------------
// Line assembly

/// What the line assembler produced.
#[derive(Debug, Clone, PartialEq)]
pub enum RawLine {
    /// A complete line (terminator removed, never empty).
    Line(Vec<u8>),
    /// A line longer than the limit (its first bytes); the rest up to the terminator was discarded.
    TooLong(Vec<u8>),
    /// Bytes with no terminator within the partial-line timeout; discarded.
    Partial(Vec<u8>),
}

/// Splits a byte stream into lines (`\n`, `\r` or `\r\n`; empty lines are ignored), with a
/// length limit and a timeout for unterminated input.
#[derive(Debug)]
pub struct LineAssembler {
    buf: Vec<u8>,
    max: usize,
    overflow: bool,
    last_byte: Option<Instant>,
    timeout: Duration,
}

impl LineAssembler {
    pub fn new(max_line_bytes: usize, partial_timeout: Duration) -> LineAssembler {
        // allocation: once per stream
        LineAssembler {
            buf: Vec::with_capacity(max_line_bytes),
            max: max_line_bytes,
            overflow: false,
            last_byte: None,
            timeout: partial_timeout,
        }
    }

    /// Feed bytes received at `now`.
    pub fn push(&mut self, bytes: &[u8], now: Instant, out: &mut Vec<RawLine>) {
        for &b in bytes {
            if b == b'\n' || b == b'\r' {
                if self.overflow {
                    out.push(RawLine::TooLong(self.buf.clone()));
                } else if !self.buf.is_empty() {
                    out.push(RawLine::Line(self.buf.clone()));
                }
                self.buf.clear();
                self.overflow = false;
            } else if self.buf.len() < self.max {
                self.buf.push(b);
            } else {
                self.overflow = true;
            }
        }
        if !bytes.is_empty() {
            self.last_byte = Some(now);
        }
    }

    /// Discard an unterminated line that has waited longer than the timeout.
    pub fn check_timeout(&mut self, now: Instant, out: &mut Vec<RawLine>) {
        if (!self.buf.is_empty() || self.overflow)
            && let Some(t) = self.last_byte
            && now.duration_since(t) >= self.timeout
        {
            out.push(RawLine::Partial(self.buf.clone()));
            self.buf.clear();
            self.overflow = false;
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Modem-status lines

/// Modem-status input lines usable as hardware triggers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModemLine {
    Cts,
    Dsr,
    Dcd,
    Ri,
}

impl ModemLine {
    pub const ALL: [ModemLine; 4] = [ModemLine::Cts, ModemLine::Dsr, ModemLine::Dcd, ModemLine::Ri];
    pub fn name(self) -> &'static str {
        match self {
            ModemLine::Cts => "cts",
            ModemLine::Dsr => "dsr",
            ModemLine::Dcd => "dcd",
            ModemLine::Ri => "ri",
        }
    }
    pub fn parse(s: &str) -> Option<ModemLine> {
        ModemLine::ALL.into_iter().find(|l| l.name() == s)
    }
    fn read(self, port: &mut dyn SerialPort) -> serialport::Result<bool> {
        match self {
            ModemLine::Cts => port.read_clear_to_send(),
            ModemLine::Dsr => port.read_data_set_ready(),
            ModemLine::Dcd => port.read_carrier_detect(),
            ModemLine::Ri => port.read_ring_indicator(),
        }
    }
}

/// Which edges of a modem line act.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EdgeMode {
    /// Inactive → active starts the trigger.
    Rising,
    /// Active → inactive starts the trigger.
    Falling,
    /// Rising starts, falling stops (the event lasts while the line is active).
    Level,
}

impl EdgeMode {
    pub const NAMES: &'static str = "rising, falling, level";
    pub fn parse(s: &str) -> Option<EdgeMode> {
        match s {
            "rising" => Some(EdgeMode::Rising),
            "falling" => Some(EdgeMode::Falling),
            "level" => Some(EdgeMode::Level),
            _ => None,
        }
    }
}

/// One modem line mapped to a trigger.
#[derive(Debug, Clone, PartialEq)]
pub struct LineTrigger {
    pub line: ModemLine,
    pub trigger: String,
    pub edge: EdgeMode,
}

/// Edge detector with debouncing: a new level counts once it was read `debounce + 1` times in a
/// row. The first reading sets the level without an edge.
#[derive(Debug, Clone)]
pub struct EdgeDetector {
    level: Option<bool>,
    candidate: bool,
    count: u32,
    debounce: u32,
}

impl EdgeDetector {
    pub fn new(debounce_polls: u32) -> EdgeDetector {
        EdgeDetector { level: None, candidate: false, count: 0, debounce: debounce_polls }
    }
    /// Feed one reading; `Some(true)` on a rising edge, `Some(false)` on a falling edge.
    pub fn feed(&mut self, v: bool) -> Option<bool> {
        let Some(level) = self.level else {
            self.level = Some(v);
            return None;
        };
        if v == level {
            self.count = 0;
            return None;
        }
        if self.count == 0 || self.candidate != v {
            self.candidate = v;
            self.count = 1;
        } else {
            self.count += 1;
        }
        if self.count > self.debounce {
            self.level = Some(v);
            self.count = 0;
            return Some(v);
        }
        None
    }
}

/// The command a line edge produces under a mapping, if any.
pub fn edge_command(map: &LineTrigger, rising: bool) -> Option<Command> {
    match (map.edge, rising) {
        (EdgeMode::Rising, true) | (EdgeMode::Falling, false) | (EdgeMode::Level, true) => {
            Some(Command::Start(map.trigger.clone()))
        }
        (EdgeMode::Level, false) => Some(Command::Stop(map.trigger.clone())),
        _ => None,
    }
}

// ---------------------------------------------------------------------------------------------
// Trigger inputs

/// Where a command came from.
#[derive(Debug, Clone, PartialEq)]
pub enum Origin {
    /// A protocol line.
    Serial,
    /// A modem-status line edge.
    Line { line: ModemLine, rising: bool },
    /// Read back from a ground-truth log (`source` as recorded there).
    Replay { source: String },
}

impl Origin {
    /// Name in the log's `source` field.
    pub fn source(&self) -> String {
        match self {
            Origin::Serial => "serial".into(),
            Origin::Line { line, .. } => line.name().into(),
            Origin::Replay { source } => source.clone(),
        }
    }
}

/// Items a trigger input hands to the controller.
#[derive(Debug, Clone, PartialEq)]
pub enum Incoming {
    /// A valid command to apply at the next frame. `cmd_seq` is the rig's sequence number
    /// (none for line edges).
    Command { cmd_seq: Option<u64>, cmd: Command, origin: Origin },
    /// A rejected line; the NAK was already sent. For the log.
    Rejected { cmd_seq: Option<u64>, reason: String, raw: String },
    /// Port trouble or a configuration note, for the log.
    Notice { message: String },
}

/// A source of trigger commands for [`crate::schedule::CampaignController`].
pub trait TriggerInput: Send {
    /// What this is (for the log), e.g. `serial:/dev/ttyACM0@115200`.
    fn describe(&self) -> String;
    /// Items due before frame `seq`: a live input returns everything received so far, a
    /// replay what took effect at frames `<= seq`.
    fn pending(&mut self, seq: u64, out: &mut Vec<Incoming>);
    /// Send a reply line to the rig (no terminator). Never blocks.
    fn reply(&mut self, _line: &str) {}
    /// Replies that could not be sent so far.
    fn dropped_replies(&self) -> u64 {
        0
    }
    /// End of stream, first step: stop taking input (what arrived so far stays pending, so
    /// the controller can still answer it).
    fn stop_reading(&mut self) {}
    /// End of stream: stop threads, flush replies.
    fn finish(&mut self) {}
    /// For a replay: the campaign fingerprint recorded in the log (hex), to warn on a mismatch.
    fn expected_fingerprint(&self) -> Option<&str> {
        None
    }
}

/// Settings of the serial reader.
#[derive(Debug, Clone)]
pub struct SerialSettings {
    pub max_line_bytes: usize,
    pub partial_timeout: Duration,
    pub poll: Duration,
    /// Consecutive identical readings (beyond the first) before a modem-line edge counts.
    pub debounce_polls: u32,
    pub lines: Vec<LineTrigger>,
}

impl Default for SerialSettings {
    fn default() -> Self {
        SerialSettings {
            max_line_bytes: DEFAULT_MAX_LINE_BYTES,
            partial_timeout: Duration::from_millis(DEFAULT_PARTIAL_TIMEOUT_MS),
            poll: Duration::from_millis(DEFAULT_POLL_MS),
            debounce_polls: 0,
            lines: Vec::new(),
        }
    }
}

type SharedPort = Arc<Mutex<Option<Box<dyn SerialPort>>>>;

/// Live triggers from a serial port: a reader thread (owns the port, parses lines, NAKs
/// garbage, polls modem lines) and a writer thread (replies).
pub struct SerialTriggers {
    name: String,
    rx: Receiver<Incoming>,
    reply_tx: Option<Sender<String>>,
    stop: Arc<AtomicBool>,
    reader: Option<JoinHandle<()>>,
    writer: Option<JoinHandle<()>>,
    dropped: u64,
}

impl SerialTriggers {
    /// Open a serial device by path.
    pub fn open(
        path: &str,
        baud: u32,
        settings: SerialSettings,
        catalog: Catalog,
    ) -> Result<SerialTriggers, TriggerError> {
        let port = open_port(path, baud, settings.poll)?;
        SerialTriggers::start(port, format!("serial:{path}@{baud}"), Some((path.to_string(), baud)), settings, catalog)
    }

    /// Use an already open port (e.g. one end of [`serialport::TTYPort::pair`]).
    pub fn from_port(
        port: Box<dyn SerialPort>,
        name: &str,
        settings: SerialSettings,
        catalog: Catalog,
    ) -> Result<SerialTriggers, TriggerError> {
        SerialTriggers::start(port, format!("serial:{name}"), None, settings, catalog)
    }

    fn start(
        mut port: Box<dyn SerialPort>,
        name: String,
        reopen: Option<(String, u32)>,
        settings: SerialSettings,
        catalog: Catalog,
    ) -> Result<SerialTriggers, TriggerError> {
        port.set_timeout(settings.poll).map_err(|source| TriggerError::Port {
            port: name.clone(),
            what: "cannot set the read timeout",
            source,
        })?;
        let out = port.try_clone().map_err(|source| TriggerError::Port {
            port: name.clone(),
            what: "cannot clone for writing",
            source,
        })?;
        let out: SharedPort = Arc::new(Mutex::new(Some(out)));
        let (tx, rx) = bounded::<Incoming>(INCOMING_QUEUE);
        let (reply_tx, reply_rx) = bounded::<String>(REPLY_QUEUE);
        let stop = Arc::new(AtomicBool::new(false));

        let w_out = out.clone();
        let w_tx = tx.clone();
        let writer = std::thread::Builder::new()
            .name("faultcam-trigger-out".into())
            .spawn(move || writer_loop(reply_rx, w_out, w_tx))
            .map_err(|e| TriggerError::Thread("trigger writer", e))?;
        let ctx = ReaderCtx { port, out, reopen, tx, replies: reply_tx.clone(), stop: stop.clone(), catalog, settings };
        let reader = std::thread::Builder::new()
            .name("faultcam-trigger-in".into())
            .spawn(move || reader_loop(ctx))
            .map_err(|e| TriggerError::Thread("trigger reader", e))?;
        Ok(SerialTriggers {
            name,
            rx,
            reply_tx: Some(reply_tx),
            stop,
            reader: Some(reader),
            writer: Some(writer),
            dropped: 0,
        })
    }

    fn stop_reader(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(h) = self.reader.take() {
            let _ = h.join();
        }
    }

    fn shutdown(&mut self) {
        self.stop_reader();
        // Dropping the last sender ends the writer after it has written what is queued.
        self.reply_tx = None;
        if let Some(h) = self.writer.take() {
            let _ = h.join();
        }
    }
}

/// Open a serial device at `baud` with read time-out `poll` (also used by the sweep's live
/// SUT reports).
pub fn open_port(path: &str, baud: u32, poll: Duration) -> Result<Box<dyn SerialPort>, TriggerError> {
    serialport::new(path, baud).timeout(poll).open().map_err(|source| TriggerError::Open {
        port: path.to_string(),
        baud,
        source,
    })
}

impl TriggerInput for SerialTriggers {
    fn describe(&self) -> String {
        self.name.clone()
    }
    fn pending(&mut self, _seq: u64, out: &mut Vec<Incoming>) {
        loop {
            match self.rx.try_recv() {
                Ok(i) => out.push(i),
                Err(TryRecvError::Empty) | Err(TryRecvError::Disconnected) => return,
            }
        }
    }
    fn reply(&mut self, line: &str) {
        let sent = match &self.reply_tx {
            Some(tx) => match tx.try_send(line.to_string()) {
                Ok(()) => true,
                Err(TrySendError::Full(_)) | Err(TrySendError::Disconnected(_)) => false,
            },
            None => false,
        };
        if !sent {
            self.dropped += 1;
        }
    }
    fn dropped_replies(&self) -> u64 {
        self.dropped
    }
    fn stop_reading(&mut self) {
        self.stop_reader();
    }
    fn finish(&mut self) {
        self.shutdown();
    }
}

impl Drop for SerialTriggers {
    fn drop(&mut self) {
        self.shutdown();
    }
}

fn writer_loop(rx: Receiver<String>, out: SharedPort, notices: Sender<Incoming>) {
    let mut failed = false;
    while let Ok(mut line) = rx.recv() {
        line.push('\n');
        let res = match out.lock() {
            Ok(mut g) => match g.as_mut() {
                Some(p) => p.write_all(line.as_bytes()).and_then(|_| p.flush()),
                None => Err(std::io::Error::other("port closed")),
            },
            Err(_) => Err(std::io::Error::other("port lock poisoned")),
        };
        match res {
            Ok(()) => failed = false,
            Err(e) if !failed => {
                failed = true;
                let _ = notices.try_send(Incoming::Notice { message: format!("cannot write reply: {e}") });
            }
            Err(_) => {}
        }
    }
}

struct ReaderCtx {
    port: Box<dyn SerialPort>,
    out: SharedPort,
    reopen: Option<(String, u32)>,
    tx: Sender<Incoming>,
    replies: Sender<String>,
    stop: Arc<AtomicBool>,
    catalog: Catalog,
    settings: SerialSettings,
}

impl ReaderCtx {
    fn nak(&self, cmd_seq: Option<u64>, reason: String, raw: &[u8]) {
        let seq = cmd_seq.map(|s| s.to_string()).unwrap_or_else(|| "-".into());
        let _ = self.replies.try_send(format!("NAK {seq} {reason}"));
        // The log entry must not block the reader on a stalled stream.
        let _ = self.tx.try_send(Incoming::Rejected { cmd_seq, reason, raw: echo(raw) });
    }

    fn handle(&self, raw: RawLine) -> bool {
        match raw {
            RawLine::Line(bytes) => match parse_line(&bytes, &self.catalog) {
                Ok((seq, cmd)) => {
                    self.tx.send(Incoming::Command { cmd_seq: Some(seq), cmd, origin: Origin::Serial }).is_ok()
                }
                Err((seq, reason)) => {
                    self.nak(seq, reason, &bytes);
                    true
                }
            },
            RawLine::TooLong(prefix) => {
                let seq = parse_line(&prefix, &Catalog::default()).err().and_then(|(s, _)| s);
                self.nak(seq, format!("line too long; limit {} bytes", self.settings.max_line_bytes), &prefix);
                true
            }
            RawLine::Partial(bytes) => {
                self.nak(
                    None,
                    format!("partial line: no terminator within {} ms", self.settings.partial_timeout.as_millis()),
                    &bytes,
                );
                true
            }
        }
    }
}

fn reader_loop(mut ctx: ReaderCtx) {
    let mut asm = LineAssembler::new(ctx.settings.max_line_bytes, ctx.settings.partial_timeout);
    let mut lines: Vec<RawLine> = Vec::new();
    let mut buf = [0u8; 256];
    let mut detectors: Vec<EdgeDetector> =
        ctx.settings.lines.iter().map(|_| EdgeDetector::new(ctx.settings.debounce_polls)).collect();
    let mut lines_ok = !ctx.settings.lines.is_empty();
    let mut port_ok = true;
    while !ctx.stop.load(Ordering::Relaxed) {
        match ctx.port.read(&mut buf) {
            Ok(0) => {
                // A closed peer can read as end of file: back off, keep the stream going.
                std::thread::sleep(ctx.settings.poll.max(Duration::from_millis(10)));
            }
            Ok(n) => {
                port_ok = true;
                asm.push(&buf[..n], Instant::now(), &mut lines);
            }
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::TimedOut | std::io::ErrorKind::Interrupted | std::io::ErrorKind::WouldBlock
                ) => {}
            Err(e) => {
                if port_ok {
                    port_ok = false;
                    let _ = ctx.tx.try_send(Incoming::Notice { message: format!("serial read failed: {e}") });
                }
                std::thread::sleep(Duration::from_millis(200));
                if let Some((path, baud)) = ctx.reopen.clone()
                    && let Ok(p) = open_port(&path, baud, ctx.settings.poll)
                    && let Ok(w) = p.try_clone()
                {
                    ctx.port = p;
                    if let Ok(mut g) = ctx.out.lock() {
                        *g = Some(w);
                    }
                    let _ = ctx.tx.try_send(Incoming::Notice { message: format!("serial port {path} reopened") });
                }
            }
        }
        asm.check_timeout(Instant::now(), &mut lines);
        for l in lines.drain(..) {
            if !ctx.handle(l) {
                return;
            }
        }
        if lines_ok {
            for (map, det) in ctx.settings.lines.iter().zip(detectors.iter_mut()) {
                match map.line.read(ctx.port.as_mut()) {
                    Ok(v) => {
                        if let Some(rising) = det.feed(v)
                            && let Some(cmd) = edge_command(map, rising)
                        {
                            let origin = Origin::Line { line: map.line, rising };
                            if ctx.tx.send(Incoming::Command { cmd_seq: None, cmd, origin }).is_err() {
                                return;
                            }
                        }
                    }
                    Err(e) => {
                        lines_ok = false;
                        let _ = ctx.tx.try_send(Incoming::Notice {
                            message: format!(
                                "modem-status lines cannot be read on this port ({e}); line triggers are off"
                            ),
                        });
                        break;
                    }
                }
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Replay

/// One trigger read back from a ground-truth log.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordedTrigger {
    /// Frame seq at which it took effect.
    pub frame: u64,
    pub cmd_seq: Option<u64>,
    /// Canonical command text.
    pub command: String,
    pub source: String,
    /// Line in the log.
    pub line: usize,
}

/// Replays the triggers of a ground-truth log at the frames where they took effect, without a
/// serial port: with the same campaign, seed and input the output bytes are identical.
pub struct TriggerReplay {
    origin: String,
    items: Vec<RecordedTrigger>,
    next: usize,
    catalog: Catalog,
    fingerprint: Option<String>,
}

impl TriggerReplay {
    /// Read the `{"record":"event","event":"trigger",...}` lines of a log.
    pub fn from_log(path: &Path, catalog: Catalog) -> Result<TriggerReplay, TriggerError> {
        let file = path.display().to_string();
        let text =
            std::fs::read_to_string(path).map_err(|source| TriggerError::ReplayIo { file: file.clone(), source })?;
        TriggerReplay::from_text(&text, &file, catalog)
    }

    /// Same from log text; `origin` names it in errors.
    pub fn from_text(text: &str, origin: &str, catalog: Catalog) -> Result<TriggerReplay, TriggerError> {
        let bad = |line: usize, message: String| TriggerError::ReplayBad { file: origin.to_string(), line, message };
        let mut items = Vec::new();
        let mut fingerprint = None;
        for (i, l) in text.lines().enumerate() {
            let line = i + 1;
            if l.trim().is_empty() {
                continue;
            }
            let v: serde_json::Value =
                serde_json::from_str(l).map_err(|e| bad(line, format!("not a JSON line: {e}")))?;
            if v.get("record").and_then(|r| r.as_str()) != Some("event") {
                continue;
            }
            match v.get("event").and_then(|r| r.as_str()) {
                Some("trigger") => {}
                Some("campaign") => {
                    if fingerprint.is_none() {
                        fingerprint = v.get("fingerprint").and_then(|f| f.as_str()).map(str::to_string);
                    }
                    continue;
                }
                _ => continue,
            }
            let frame = v
                .get("seq")
                .and_then(|s| s.as_u64())
                .ok_or_else(|| bad(line, "trigger record without a frame 'seq'".into()))?;
            let command = v
                .get("command")
                .and_then(|s| s.as_str())
                .ok_or_else(|| bad(line, "trigger record without 'command'".into()))?
                .to_string();
            // Check now, so a log from another campaign fails before the run.
            parse_command(&command, &catalog)
                .map_err(|e| bad(line, format!("recorded command '{command}' does not fit this campaign: {e}")))?;
            if let Some(prev) = items.last().map(|p: &RecordedTrigger| p.frame)
                && frame < prev
            {
                return Err(bad(line, format!("trigger frames go backwards ({prev} then {frame})")));
            }
            items.push(RecordedTrigger {
                frame,
                cmd_seq: v.get("cmd_seq").and_then(|s| s.as_u64()),
                command,
                source: v.get("source").and_then(|s| s.as_str()).unwrap_or("serial").to_string(),
                line,
            });
        }
        Ok(TriggerReplay { origin: origin.to_string(), items, next: 0, catalog, fingerprint })
    }

    /// The recorded triggers.
    pub fn items(&self) -> &[RecordedTrigger] {
        &self.items
    }
}

impl TriggerInput for TriggerReplay {
    fn describe(&self) -> String {
        format!("replay:{} ({} triggers)", self.origin, self.items.len())
    }
    fn expected_fingerprint(&self) -> Option<&str> {
        self.fingerprint.as_deref()
    }
    fn pending(&mut self, seq: u64, out: &mut Vec<Incoming>) {
        while let Some(r) = self.items.get(self.next) {
            if r.frame > seq {
                break;
            }
            self.next += 1;
            if r.frame < seq {
                out.push(Incoming::Notice {
                    message: format!(
                        "recorded trigger '{}' took effect at frame {} but this stream has no such frame; applied at frame {seq}",
                        r.command, r.frame
                    ),
                });
            }
            match parse_command(&r.command, &self.catalog) {
                Ok(cmd) => out.push(Incoming::Command {
                    cmd_seq: r.cmd_seq,
                    cmd,
                    origin: Origin::Replay { source: r.source.clone() },
                }),
                Err(e) => out.push(Incoming::Notice { message: format!("cannot replay '{}': {e}", r.command) }),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cat() -> Catalog {
        Catalog {
            names: vec!["flash".into(), "storm".into()],
            effects: vec![
                ("gain_offset".into(), crate::faults::registry::find("gain_offset").unwrap().info),
                ("gaussian_noise".into(), crate::faults::registry::find("gaussian_noise").unwrap().info),
                ("gaussian_noise".into(), crate::faults::registry::find("gaussian_noise").unwrap().info),
            ],
        }
    }

    #[test]
    fn parses_every_command_and_round_trips_text() {
        let c = cat();
        let cases: &[(&str, Command)] = &[
            ("1 START flash", Command::Start("flash".into())),
            ("  2 stop storm ", Command::Stop("storm".into())),
            ("3 ARM", Command::Arm),
            ("4 DISARM", Command::Disarm),
            ("5 PING", Command::Ping),
            ("6 MARK run 3 begins", Command::Mark("run 3 begins".into())),
            (
                "7 SET gain_offset.gain 2.5",
                Command::Set { index: 0, target: SetTarget::Param { param: 0, value: 2.5 } },
            ),
            ("8 SET gaussian_noise#2.enabled false", Command::Set { index: 2, target: SetTarget::Enabled(false) }),
        ];
        for (line, want) in cases {
            let (seq, cmd) = parse_line(line.as_bytes(), &c).unwrap();
            assert_eq!(&cmd, want, "{line}");
            assert_eq!(seq, line.split_whitespace().next().unwrap().parse::<u64>().unwrap());
            assert_eq!(parse_command(&cmd.text(&c), &c).unwrap(), cmd, "{line}");
        }
    }

    #[test]
    fn rejections_carry_seq_and_reason() {
        let c = cat();
        let err = |l: &[u8]| parse_line(l, &c).unwrap_err();
        assert_eq!(err(b"hello").0, None);
        assert!(err(b"hello").1.contains("sequence number"));
        let (s, r) = err(b"9 FIRE flash");
        assert_eq!(s, Some(9));
        assert!(r.contains("unknown command 'FIRE'") && r.contains("START, STOP"), "{r}");
        let (s, r) = err(b"10 START nope");
        assert_eq!(s, Some(10));
        assert!(r.contains("unknown event or trigger 'nope'") && r.contains("flash, storm"), "{r}");
        let (_, r) = err(b"11 SET gain_offset.gain 9");
        assert!(r.contains("out of range") && r.contains("0..=4"), "{r}");
        let (_, r) = err(b"12 SET gaussian_noise.sigma_dn 1");
        assert!(r.contains("configured 2 times") && r.contains("gaussian_noise#1"), "{r}");
        let (_, r) = err(b"13 SET gain_offset.nope 1");
        assert!(r.contains("unknown parameter 'nope'") && r.contains("gain"), "{r}");
        let (s, r) = err(b"14 START fl\xffash");
        assert_eq!(s, Some(14));
        // 0-based offset of the 0xff byte in the whole line, as the rig sent it.
        assert!(r.contains("invalid UTF-8 at byte 11"), "{r}");
        let (_, r) = err(b"15 START");
        assert!(r.contains("START takes 1 argument"), "{r}");
        assert!(err(b"-1 PING").0.is_none());
        assert!(err(b"12x PING").0.is_none());
    }

    #[test]
    fn assembler_splits_limits_and_times_out() {
        let t0 = Instant::now();
        let mut a = LineAssembler::new(8, Duration::from_millis(100));
        let mut out = Vec::new();
        a.push(b"1 PI", t0, &mut out);
        assert!(out.is_empty());
        a.push(b"NG\r\n\n2 ARM\r0123456789abc\n3", t0, &mut out);
        assert_eq!(
            out,
            vec![
                RawLine::Line(b"1 PING".to_vec()),
                RawLine::Line(b"2 ARM".to_vec()),
                RawLine::TooLong(b"01234567".to_vec())
            ]
        );
        out.clear();
        a.check_timeout(t0 + Duration::from_millis(50), &mut out);
        assert!(out.is_empty());
        a.check_timeout(t0 + Duration::from_millis(100), &mut out);
        assert_eq!(out, vec![RawLine::Partial(b"3".to_vec())]);
    }

    #[test]
    fn edge_detector_debounces() {
        let mut d = EdgeDetector::new(0);
        assert_eq!(d.feed(false), None);
        assert_eq!(d.feed(true), Some(true));
        assert_eq!(d.feed(true), None);
        assert_eq!(d.feed(false), Some(false));
        let mut d = EdgeDetector::new(2);
        let seq = [false, true, false, true, true, true, true, false, false, false];
        let edges: Vec<_> = seq.iter().map(|&v| d.feed(v)).collect();
        // The glitch at index 1 is ignored; the level counts after three equal readings.
        assert_eq!(edges, vec![None, None, None, None, None, Some(true), None, None, None, Some(false)]);
        let m = LineTrigger { line: ModemLine::Cts, trigger: "flash".into(), edge: EdgeMode::Level };
        assert_eq!(edge_command(&m, true), Some(Command::Start("flash".into())));
        assert_eq!(edge_command(&m, false), Some(Command::Stop("flash".into())));
        let m = LineTrigger { edge: EdgeMode::Falling, ..m };
        assert_eq!(edge_command(&m, true), None);
    }
}
