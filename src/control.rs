//! Controllers change the fault chain between frames: scripted timelines
//! ([`crate::schedule`]) and serial-port triggers ([`crate::trigger`]). The pipeline calls
//! every controller before each frame enters the chain and after it has been handled.

use crate::faults::chain::Chain;
use crate::gtlog::FrameStatus;

/// An event for the ground-truth log (event start/stop, trigger, acknowledgement, ...).
/// The pipeline writes each one as a `{"record":"event", ...}` line.
pub type LogEvent = serde_json::Value;

/// Something that drives the chain over time.
pub trait Controller: Send {
    /// Before frame `seq` enters the chain. `t_ns` is the stream time (ns since the stream
    /// started; for files with timestamps, the recorded time). May change parameters or
    /// enable/disable entries of `chain`, and push log events.
    fn before_frame(
        &mut self,
        seq: u64,
        t_ns: u64,
        chain: &mut Chain,
        events: &mut Vec<LogEvent>,
    ) -> anyhow::Result<()>;
    /// After frame `seq` was handled (delivered or dropped), e.g. to acknowledge a trigger
    /// with the frame at which it took effect.
    fn after_frame(&mut self, _seq: u64, _t_ns: u64, _status: FrameStatus, _events: &mut Vec<LogEvent>) {}
    /// At the end of the stream.
    fn finish(&mut self, _events: &mut Vec<LogEvent>) {}
}
