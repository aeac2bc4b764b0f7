//! The `faultcam` element (a `GstBaseTransform` working in place).
//!
//! Per buffer, in this order (the same steps as `faultcam run`'s fault stage, and the same
//! chain call as `faultcam apply`, so the bytes are identical for the same config, seed and
//! frame index):
//! 1. the buffer's frame index `seq` is the number of buffers the element has seen since it
//!    started (0-based; a flush or a restart from NULL/READY begins again at 0) and its stream
//!    time `t_ns` is its PTS minus the first buffer's PTS (0 when buffers carry no PTS);
//! 2. the campaign controller (`[[events]]`, `[triggers]`, serial triggers from the `trigger`
//!    property) updates the chain for (`seq`, `t_ns`): `at_frame`/`duration_frames` events run
//!    on the frame index, `at_s`/`duration_s` events on the PTS;
//! 3. the pixels are copied into a reused faultcam frame (BGR is swapped to RGB and back, so
//!    colour effects keep their meaning), the chain runs, and the result is copied back;
//! 4. a frame dropped by an effect (`frame_drop`, a held `reorder`/`frame_freeze` frame) is
//!    dropped from the stream (frames `reorder` still holds at EOS are pushed before the EOS);
//!    a temporal delay (`frame_delay`, `jitter`) is added to the PTS;
//! 5. the ground-truth log (`log`) gets the frame's record and the controller's events, masks
//!    (`masks`) are written as `frame_NNNNNN.*`, and an element message named
//!    [`MESSAGE_NAME`] is posted on the bus with what was applied (`post-messages`).

use faultcam::control::{Controller, LogEvent};
use faultcam::frame::FrameError;
use faultcam::gtlog::{FrameRecord, FrameStatus, GroundTruthLog};
use faultcam::masks::{MaskOptions, MaskRecord, MaskRecorder, mask_stem};
use faultcam::pipeline::HOLDING_EFFECTS;
use faultcam::pipeline::pool::{copy_rows_into, copy_rows_out};
use faultcam::schedule::{TriggerOptions, controllers_from_config};
use faultcam::{Chain, FaultConfig, Frame, FrameData, FrameReport, Outcome, PixelFormat};
use gst::glib;
use gst::prelude::*;
use gst::subclass::prelude::*;
use gst_base::subclass::prelude::*;
use gst_video::prelude::*;
use std::path::PathBuf;
use std::sync::{LazyLock, Mutex};

/// Name of the element message posted for every buffer (fields: `seq` u64, `pts` u64 ns or
/// absent, `stream-time` u64 ns, `status` string, `dropped-by` string, `effects` string
/// (comma-separated names in application order), `delay` u64 ns, `record` string (the
/// ground-truth log's JSON line for the frame)).
pub const MESSAGE_NAME: &str = "faultcam-frame";

static CAT: LazyLock<gst::DebugCategory> = LazyLock::new(|| {
    gst::DebugCategory::new("faultcam", gst::DebugColorFlags::empty(), Some("faultcam fault injection"))
});

glib::wrapper! {
    /// The `faultcam` element: applies a faultcam fault config to every video buffer in place.
    /// Properties: `config` (TOML path, required), `seed` (overrides the config's), `log`
    /// (ground-truth JSONL path), `masks` (folder for per-pixel fault masks), `trigger` (serial
    /// device for trigger commands), `post-messages` (default true).
    pub struct FaultCamFilter(ObjectSubclass<imp::FaultCamFilter>)
        @extends gst_base::BaseTransform, gst::Element, gst::Object;
}

pub(crate) fn register(plugin: Option<&gst::Plugin>) -> Result<(), glib::BoolError> {
    gst::Element::register(plugin, "faultcam", gst::Rank::NONE, FaultCamFilter::static_type())
}

/// Video formats the element accepts and the faultcam layout each maps to.
fn map_format(f: gst_video::VideoFormat) -> Option<(PixelFormat, bool)> {
    match f {
        gst_video::VideoFormat::Gray8 => Some((PixelFormat::Mono8, false)),
        gst_video::VideoFormat::Gray16Le => Some((PixelFormat::Mono16, false)),
        gst_video::VideoFormat::Rgb => Some((PixelFormat::Rgb8, false)),
        gst_video::VideoFormat::Bgr => Some((PixelFormat::Rgb8, true)),
        _ => None,
    }
}

const FORMATS: [gst_video::VideoFormat; 4] = [
    gst_video::VideoFormat::Gray8,
    gst_video::VideoFormat::Gray16Le,
    gst_video::VideoFormat::Rgb,
    gst_video::VideoFormat::Bgr,
];

/// Swap the first and third byte of every RGB pixel of a row (RGB <-> BGR).
fn swap_rb(row: &mut [u8]) {
    for p in row.chunks_exact_mut(3) {
        p.swap(0, 2);
    }
}

/// Copy a mapped plane (rows `stride` bytes apart) into the packed frame (the pipeline's
/// `copy_rows_into`), BGR turned into RGB.
fn copy_in(src: &[u8], stride: usize, bgr: bool, frame: &mut Frame) -> Result<(), FrameError> {
    copy_rows_into(frame, src, stride)?;
    if bgr {
        let (row, fs, h) = (frame.row_len(), frame.stride, frame.height as usize);
        if let FrameData::U8(d) = &mut frame.data {
            d.chunks_exact_mut(fs).take(h).for_each(|r| swap_rb(&mut r[..row]));
        }
    }
    Ok(())
}

/// Copy the frame's samples back into the mapped plane (the pipeline's `copy_rows_out`; padding
/// bytes untouched), RGB turned back into BGR.
fn copy_out(frame: &Frame, dst: &mut [u8], stride: usize, bgr: bool) -> Result<(), FrameError> {
    copy_rows_out(frame, dst, stride)?;
    if bgr {
        let row = frame.row_len();
        for y in 0..frame.height as usize {
            swap_rb(&mut dst[y * stride..y * stride + row]);
        }
    }
    Ok(())
}

/// Why the chain's output `frame` cannot go into a buffer of the negotiated layout (a temporal
/// effect may hand out a frame of another size), or `None` when it fits.
fn layout_mismatch(frame: &Frame, info: &gst_video::VideoInfo, format: PixelFormat) -> Option<String> {
    (frame.width != info.width() || frame.height != info.height() || frame.format != format).then(|| {
        format!(
            "the chain returned a {}x{} {} frame for a {}x{} {} stream",
            frame.width,
            frame.height,
            frame.format,
            info.width(),
            info.height(),
            format
        )
    })
}

/// A frame's log status: failed on an error, else what the chain decided.
fn status_of(failed: bool, outcome: Outcome) -> FrameStatus {
    match (failed, outcome) {
        (true, _) => FrameStatus::Failed,
        (false, Outcome::Drop) => FrameStatus::DroppedByFault,
        (false, Outcome::Keep) => FrameStatus::Delivered,
    }
}

/// A new buffer holding a drained frame, laid out as the negotiated caps say.
fn drained_buffer(
    frame: &Frame,
    info: &gst_video::VideoInfo,
    bgr: bool,
    format: PixelFormat,
) -> Result<gst::Buffer, String> {
    if let Some(e) = layout_mismatch(frame, info, format) {
        return Err(e);
    }
    let mut buf = gst::Buffer::with_size(info.size()).map_err(|e| format!("cannot allocate a buffer: {e}"))?;
    {
        let b = buf.get_mut().ok_or("new buffer not writable")?;
        let mut vf = gst_video::VideoFrameRef::from_buffer_ref_writable(b, info)
            .map_err(|_| "cannot map the new buffer".to_string())?;
        let stride = vf.plane_stride()[0] as usize;
        let data = vf.plane_data_mut(0).map_err(|e| e.to_string())?;
        copy_out(frame, data, stride, bgr).map_err(|e| e.to_string())?;
    }
    Ok(buf)
}

mod imp {
    use super::*;

    #[derive(Debug, Clone)]
    struct Settings {
        config: Option<PathBuf>,
        seed: Option<u64>,
        log: Option<PathBuf>,
        masks: Option<PathBuf>,
        trigger: Option<String>,
        post_messages: bool,
    }

    impl Default for Settings {
        fn default() -> Self {
            Settings { config: None, seed: None, log: None, masks: None, trigger: None, post_messages: true }
        }
    }

    /// Everything a running element owns (created in `start`, dropped in `stop`).
    struct State {
        chain: Chain,
        controllers: Vec<Box<dyn Controller>>,
        report: FrameReport,
        /// allocation: once per caps (the packed copy the chain works on).
        frame: Option<Frame>,
        info: Option<gst_video::VideoInfo>,
        format: PixelFormat,
        bgr: bool,
        log: Option<GroundTruthLog>,
        masks: Option<(PathBuf, MaskRecorder)>,
        events: Vec<LogEvent>,
        seq: u64,
        first_pts: Option<u64>,
        delivered: u64,
        dropped: u64,
        failed: u64,
        /// Frames held back by an effect (`reorder`): released later, or at EOS.
        held: u64,
        /// Held frames released at EOS (each also counted by its final status).
        drained: u64,
        /// PTS and duration of the last buffer (the time slots of frames released at EOS).
        last_pts: Option<u64>,
        last_duration: Option<u64>,
    }

    impl State {
        /// Count a frame by its final status, write its record (after the pending campaign
        /// events) to the log and build the element message (`post`). Returns a log write
        /// error, if any, and the message.
        #[allow(clippy::too_many_arguments)]
        fn account(
            &mut self,
            seq: u64,
            t_ns: u64,
            pts: Option<u64>,
            status: FrameStatus,
            error: Option<&str>,
            masks: Option<&MaskRecord>,
            post: bool,
            src: &super::FaultCamFilter,
        ) -> (Option<String>, Option<gst::Message>) {
            match status {
                FrameStatus::Delivered => self.delivered += 1,
                FrameStatus::Failed => self.failed += 1,
                FrameStatus::DroppedByFault if self.report.dropped_by.is_some_and(|e| HOLDING_EFFECTS.contains(&e)) => {
                    self.held += 1
                }
                _ => self.dropped += 1,
            }
            let mut rec = FrameRecord::from_report(seq, t_ns, &self.report);
            rec.status = status;
            rec.error = error;
            rec.masks = masks;
            let mut log_error = None;
            if let Some(log) = self.log.as_mut()
                && let Err(e) = self.events.iter().try_for_each(|e| log.event(e)).and_then(|_| log.frame(&rec))
            {
                log_error = Some(format!("cannot write the ground-truth log: {e}"));
            }
            self.events.clear();
            if !post {
                return (log_error, None);
            }
            // allocation: per buffer, only with post-messages (the message itself).
            let effects: Vec<&str> = self.report.applied.iter().map(|a| a.name).collect();
            let mut s = gst::Structure::builder(MESSAGE_NAME)
                .field("seq", seq)
                .field("stream-time", t_ns)
                .field("status", serde_json::to_value(status).ok().and_then(|v| v.as_str().map(String::from)))
                .field("effects", effects.join(","))
                .field("delay", self.report.delay_ns)
                .field("record", serde_json::to_string(&rec).unwrap_or_default());
            if let Some(p) = pts {
                s = s.field("pts", p);
            }
            if let Some(d) = self.report.dropped_by {
                s = s.field("dropped-by", d);
            }
            (log_error, Some(gst::message::Element::builder(s.build()).src(src).build()))
        }

        fn write_events(&mut self) -> Result<(), String> {
            if let Some(log) = self.log.as_mut() {
                for e in self.events.drain(..) {
                    log.event(&e).map_err(|e| format!("cannot write the ground-truth log: {e}"))?;
                }
            }
            self.events.clear();
            Ok(())
        }
    }

    #[derive(Default)]
    pub struct FaultCamFilter {
        settings: Mutex<Settings>,
        state: Mutex<Option<State>>,
    }

    #[glib::object_subclass]
    impl ObjectSubclass for FaultCamFilter {
        const NAME: &'static str = "GstFaultCam";
        type Type = super::FaultCamFilter;
        type ParentType = gst_base::BaseTransform;
    }

    fn path_prop(value: &glib::Value) -> Option<PathBuf> {
        value.get::<Option<String>>().expect("type checked upstream").filter(|s| !s.is_empty()).map(PathBuf::from)
    }

    impl ObjectImpl for FaultCamFilter {
        fn properties() -> &'static [glib::ParamSpec] {
            static PROPS: LazyLock<Vec<glib::ParamSpec>> = LazyLock::new(|| {
                vec![
                    glib::ParamSpecString::builder("config")
                        .nick("Fault config")
                        .blurb("Fault configuration / campaign (TOML; see `faultcam effects`). Required.")
                        .mutable_ready()
                        .build(),
                    glib::ParamSpecUInt64::builder("seed")
                        .nick("Campaign seed")
                        .blurb("Campaign seed, 0..=18446744073709551615 (default: the config's `seed`)")
                        .default_value(0)
                        .mutable_ready()
                        .build(),
                    glib::ParamSpecString::builder("log")
                        .nick("Ground-truth log")
                        .blurb("Ground-truth log path (JSON Lines: one record per buffer, campaign events, summary)")
                        .mutable_ready()
                        .build(),
                    glib::ParamSpecString::builder("masks")
                        .nick("Mask folder")
                        .blurb("Folder for per-pixel fault masks (frame_NNNNNN.labels.png; created if missing)")
                        .mutable_ready()
                        .build(),
                    glib::ParamSpecString::builder("trigger")
                        .nick("Trigger port")
                        .blurb("Serial device for trigger commands (START/STOP/SET ...; overrides [triggers] port)")
                        .mutable_ready()
                        .build(),
                    glib::ParamSpecBoolean::builder("post-messages")
                        .nick("Post messages")
                        .blurb("Post a faultcam-frame element message per buffer with what was applied")
                        .default_value(true)
                        .mutable_playing()
                        .build(),
                ]
            });
            PROPS.as_ref()
        }

        fn set_property(&self, _id: usize, value: &glib::Value, pspec: &glib::ParamSpec) {
            let mut s = self.settings.lock().unwrap();
            match pspec.name() {
                "config" => s.config = path_prop(value),
                "seed" => s.seed = Some(value.get().expect("type checked upstream")),
                "log" => s.log = path_prop(value),
                "masks" => s.masks = path_prop(value),
                "trigger" => s.trigger = path_prop(value).map(|p| p.display().to_string()),
                "post-messages" => s.post_messages = value.get().expect("type checked upstream"),
                other => unreachable!("unknown property {other}"),
            }
        }

        fn property(&self, _id: usize, pspec: &glib::ParamSpec) -> glib::Value {
            let s = self.settings.lock().unwrap();
            let path = |p: &Option<PathBuf>| p.as_ref().map(|p| p.display().to_string()).to_value();
            match pspec.name() {
                "config" => path(&s.config),
                "seed" => s.seed.unwrap_or(0).to_value(),
                "log" => path(&s.log),
                "masks" => path(&s.masks),
                "trigger" => s.trigger.to_value(),
                "post-messages" => s.post_messages.to_value(),
                other => unreachable!("unknown property {other}"),
            }
        }
    }

    impl GstObjectImpl for FaultCamFilter {}

    impl FaultCamFilter {
        /// At EOS: the frames effects still hold (`reorder`) go through the effects after the
        /// one that held them and are pushed downstream after the last buffer (PTS: the last
        /// buffer's + k buffer durations + the frame's delay; offset: the frame's `seq`), each
        /// with its own log record and message (its own `seq` and stream time), so
        /// every input buffer is accounted for (`held` in the summary counts the hold records,
        /// `drained` the releases).
        fn drain_at_eos(&self) {
            let post = self.settings.lock().unwrap().post_messages;
            loop {
                let mut guard = self.state.lock().unwrap();
                let Some(st) = guard.as_mut() else { return };
                let Some(info) = st.info.clone() else { return };
                let Some((frame, result)) = st.chain.drain_next(&mut st.report) else { return };
                st.drained += 1;
                let (outcome, mut error) = match result {
                    Ok(o) => (o, None),
                    Err(e) => (Outcome::Drop, Some(e.to_string())),
                };
                // As in the stream, a released frame's bytes go out in the next time slot:
                // after the last buffer, one buffer duration apart (plus its own delay).
                let slot = st.drained * st.last_duration.unwrap_or(0);
                let pts = st.last_pts.map(|p| p + slot + st.report.delay_ns);
                let mut out = None;
                if outcome == Outcome::Keep && error.is_none() {
                    // allocation: end of stream only (one buffer per held frame).
                    match drained_buffer(&frame, &info, st.bgr, st.format) {
                        Ok(mut b) => {
                            if let Some(b) = b.get_mut() {
                                b.set_pts(pts.map(gst::ClockTime::from_nseconds));
                                b.set_offset(frame.seq);
                            }
                            out = Some(b);
                        }
                        Err(e) => error = Some(e),
                    }
                }
                drop(guard);
                // Push without the state lock (downstream may call back into the element).
                if let Some(b) = out
                    && let Err(flow) = self.obj().src_pad().push(b)
                {
                    error = Some(format!("downstream refused the held frame at EOS: {flow:?}"));
                }
                let status = status_of(error.is_some(), outcome);
                let mut guard = self.state.lock().unwrap();
                let Some(st) = guard.as_mut() else { return };
                let (log_error, msg) =
                    st.account(frame.seq, frame.pts_ns, pts, status, error.as_deref(), None, post, &self.obj());
                drop(guard);
                if let Some(msg) = msg {
                    let _ = self.obj().post_message(msg);
                }
                if let Some(e) = log_error {
                    gst::element_imp_error!(self, gst::StreamError::Failed, ["frame {}: {}", frame.seq, e]);
                    return;
                }
            }
        }
    }

    impl ElementImpl for FaultCamFilter {
        fn metadata() -> Option<&'static gst::subclass::ElementMetadata> {
            static META: LazyLock<gst::subclass::ElementMetadata> = LazyLock::new(|| {
                gst::subclass::ElementMetadata::new(
                    "faultcam fault injection",
                    "Filter/Effect/Video",
                    "Applies physically modelled camera faults (a faultcam fault config and campaign) to raw video; \
                     bytes identical to `faultcam apply` for the same config, seed and frame index",
                    "faultcam developers",
                )
            });
            Some(&*META)
        }

        fn pad_templates() -> &'static [gst::PadTemplate] {
            static TEMPLATES: LazyLock<Vec<gst::PadTemplate>> = LazyLock::new(|| {
                let caps = gst_video::VideoCapsBuilder::new().format_list(FORMATS).build();
                vec![
                    gst::PadTemplate::new("src", gst::PadDirection::Src, gst::PadPresence::Always, &caps)
                        .expect("valid template"),
                    gst::PadTemplate::new("sink", gst::PadDirection::Sink, gst::PadPresence::Always, &caps)
                        .expect("valid template"),
                ]
            });
            TEMPLATES.as_ref()
        }
    }

    impl BaseTransformImpl for FaultCamFilter {
        const MODE: gst_base::subclass::BaseTransformMode = gst_base::subclass::BaseTransformMode::AlwaysInPlace;
        const PASSTHROUGH_ON_SAME_CAPS: bool = false;
        const TRANSFORM_IP_ON_PASSTHROUGH: bool = false;

        fn start(&self) -> Result<(), gst::ErrorMessage> {
            let s = self.settings.lock().unwrap().clone();
            let settings_err = |m: String| gst::error_msg!(gst::ResourceError::Settings, ["{}", m]);
            let Some(config) = s.config.clone() else {
                return Err(settings_err("property `config` is not set: give the fault config (TOML) path".into()));
            };
            let mut cfg = FaultConfig::load(&config).map_err(|e| settings_err(e.to_string()))?;
            if let Some(seed) = s.seed {
                cfg.seed = seed;
            }
            let chain = Chain::from_config(&cfg).map_err(|e| settings_err(format!("{}: {e}", config.display())))?;
            let opts = TriggerOptions { serial: s.trigger.clone(), ..TriggerOptions::default() };
            let controllers = controllers_from_config(&cfg, &opts).map_err(|e| settings_err(e.to_string()))?;
            let mut log = match &s.log {
                Some(p) => Some(GroundTruthLog::create(p).map_err(|e| {
                    gst::error_msg!(gst::ResourceError::OpenWrite, ["log {}: cannot create: {}", p.display(), e])
                })?),
                None => None,
            };
            let masks = match &s.masks {
                Some(dir) => {
                    std::fs::create_dir_all(dir).map_err(|e| {
                        gst::error_msg!(
                            gst::ResourceError::OpenWrite,
                            ["masks {}: cannot create: {}", dir.display(), e]
                        )
                    })?;
                    Some((dir.clone(), MaskRecorder::new(MaskOptions::default())))
                }
                None => None,
            };
            if let Some(log) = log.as_mut() {
                log.event(&serde_json::json!({
                    "event": "start",
                    "source": "gstreamer",
                    "element": self.obj().name().as_str(),
                    "faults": config.display().to_string(),
                    "seed": cfg.seed,
                    "effects": chain.entries().iter().map(|e| e.name()).collect::<Vec<_>>(),
                    "masks": s.masks.as_ref().map(|m| m.display().to_string()),
                }))
                .map_err(|e| gst::error_msg!(gst::ResourceError::Write, ["log: {}", e]))?;
            }
            gst::info!(CAT, imp = self, "started: {} effects, seed {}", chain.entries().len(), cfg.seed);
            *self.state.lock().unwrap() = Some(State {
                chain,
                controllers,
                report: FrameReport::default(),
                frame: None,
                info: None,
                format: PixelFormat::Mono8,
                bgr: false,
                log,
                masks,
                events: Vec::new(),
                seq: 0,
                first_pts: None,
                delivered: 0,
                dropped: 0,
                failed: 0,
                held: 0,
                drained: 0,
                last_pts: None,
                last_duration: None,
            });
            Ok(())
        }

        fn stop(&self) -> Result<(), gst::ErrorMessage> {
            let Some(mut st) = self.state.lock().unwrap().take() else { return Ok(()) };
            // Frames an effect still holds (stopped without EOS): never pushed, logged as failed.
            let mut report = FrameReport::default();
            while let Some((frame, _)) = st.chain.drain_next(&mut report) {
                st.report = std::mem::take(&mut report);
                st.drained += 1;
                let _ = st.account(
                    frame.seq,
                    frame.pts_ns,
                    None,
                    FrameStatus::Failed,
                    Some("held by an effect when the element stopped before EOS: never pushed"),
                    None,
                    false,
                    &self.obj(),
                );
            }
            for c in &mut st.controllers {
                c.finish(&mut st.events);
            }
            let events_written = st.write_events();
            if let Some(log) = st.log.as_mut() {
                let summary = serde_json::json!({
                    "frames_in": st.seq,
                    "delivered": st.delivered,
                    "dropped": st.dropped,
                    "failed": st.failed,
                    "held": st.held,
                    "drained": st.drained,
                    "unaccounted": 0,
                    "stopped_by": "element stopped",
                    "error": events_written.as_ref().err(),
                });
                log.summary(&summary)
                    .and_then(|_| log.flush())
                    .map_err(|e| gst::error_msg!(gst::ResourceError::Write, ["log: {}", e]))?;
            }
            Ok(())
        }

        fn set_caps(&self, incaps: &gst::Caps, outcaps: &gst::Caps) -> Result<(), gst::LoggableError> {
            let info = gst_video::VideoInfo::from_caps(incaps)
                .map_err(|_| gst::loggable_error!(CAT, "cannot parse caps {incaps}"))?;
            let Some((format, bgr)) = map_format(info.format()) else {
                return Err(gst::loggable_error!(
                    CAT,
                    "format {:?} is not accepted; accepted: GRAY8, GRAY16_LE, RGB, BGR",
                    info.format()
                ));
            };
            if incaps != outcaps {
                return Err(gst::loggable_error!(CAT, "in-place filter: output caps must equal input caps"));
            }
            let mut guard = self.state.lock().unwrap();
            let st = guard.as_mut().ok_or_else(|| gst::loggable_error!(CAT, "caps before start"))?;
            let frame = Frame::new(info.width(), info.height(), format)
                .map_err(|e| gst::loggable_error!(CAT, "caps {incaps}: {e}"))?;
            st.frame = Some(frame);
            st.format = format;
            st.bgr = bgr;
            st.info = Some(info);
            Ok(())
        }

        fn sink_event(&self, event: gst::Event) -> bool {
            if let gst::EventView::FlushStop(_) = event.view()
                && let Some(st) = self.state.lock().unwrap().as_mut()
            {
                // A seek starts a new stream: frame indices and stream time begin again.
                st.seq = 0;
                st.first_pts = None;
            }
            if let gst::EventView::Eos(_) = event.view() {
                self.drain_at_eos();
            }
            self.parent_sink_event(event)
        }

        fn transform_ip(&self, buf: &mut gst::BufferRef) -> Result<gst::FlowSuccess, gst::FlowError> {
            let post = self.settings.lock().unwrap().post_messages;
            let mut guard = self.state.lock().unwrap();
            let st = guard.as_mut().ok_or(gst::FlowError::Flushing)?;
            let (Some(info), Some(frame)) = (st.info.as_ref(), st.frame.as_mut()) else {
                return Err(gst::FlowError::NotNegotiated);
            };
            let seq = st.seq;
            st.seq += 1;
            let pts = buf.pts().map(|p| p.nseconds());
            st.last_pts = pts;
            st.last_duration = buf.duration().map(|d| d.nseconds());
            let t_ns = match (pts, st.first_pts) {
                (Some(p), Some(f)) => p.saturating_sub(f),
                (Some(p), None) => {
                    st.first_pts = Some(p);
                    0
                }
                (None, _) => 0,
            };

            for c in &mut st.controllers {
                if let Err(e) = c.before_frame(seq, t_ns, &mut st.chain, &mut st.events) {
                    gst::element_imp_error!(
                        self,
                        gst::StreamError::Failed,
                        ["campaign controller failed before frame {}: {:#}", seq, e]
                    );
                    return Err(gst::FlowError::Error);
                }
            }

            // 1. Into the packed frame.
            {
                let vf = gst_video::VideoFrameRef::from_buffer_ref_readable(buf, info).map_err(|_| {
                    gst::element_imp_error!(self, gst::CoreError::Failed, ["cannot map buffer {} for reading", seq]);
                    gst::FlowError::Error
                })?;
                let stride = vf.plane_stride()[0] as usize;
                let data = vf.plane_data(0).map_err(|_| gst::FlowError::Error)?;
                copy_in(data, stride, st.bgr, frame).map_err(|_| gst::FlowError::Error)?;
            }
            frame.seq = seq;
            frame.pts_ns = t_ns;

            // 2. The chain (the call `faultcam apply` makes).
            let result = match st.masks.as_mut() {
                Some((_, rec)) => st.chain.apply_recording(frame, &mut st.report, rec),
                None => st.chain.apply(frame, &mut st.report),
            };
            let mut mask_record = None;
            let mut error: Option<String> = None;
            let outcome = match result {
                Ok(o) => o,
                Err(e) => {
                    error = Some(e.to_string());
                    Outcome::Drop
                }
            };
            if outcome == Outcome::Keep {
                // 3. Back into the buffer (a temporal effect may have handed out another frame of
                // the same size: its bytes go out under this buffer's timestamps).
                if let Some(e) = layout_mismatch(frame, info, st.format) {
                    error = Some(e);
                } else {
                    let mut vf = gst_video::VideoFrameRef::from_buffer_ref_writable(buf, info).map_err(|_| {
                        gst::element_imp_error!(
                            self,
                            gst::CoreError::Failed,
                            ["cannot map buffer {} for writing", seq]
                        );
                        gst::FlowError::Error
                    })?;
                    let stride = vf.plane_stride()[0] as usize;
                    let data = vf.plane_data_mut(0).map_err(|_| gst::FlowError::Error)?;
                    copy_out(frame, data, stride, st.bgr).map_err(|_| gst::FlowError::Error)?;
                }
                if error.is_none()
                    && let Some((dir, rec)) = st.masks.as_mut()
                {
                    match rec.write(dir, &mask_stem(None, frame.seq)) {
                        Ok(r) => mask_record = Some(r),
                        Err(e) => error = Some(e.to_string()),
                    }
                }
            }
            let delay = st.report.delay_ns;
            if outcome == Outcome::Keep
                && delay > 0
                && let Some(p) = buf.pts()
            {
                buf.set_pts(p + gst::ClockTime::from_nseconds(delay));
            }
            let status = status_of(error.is_some(), outcome);
            for c in &mut st.controllers {
                c.after_frame(seq, t_ns, status, &mut st.events);
            }

            // 4. Log and message.
            let (log_error, msg) =
                st.account(seq, t_ns, pts, status, error.as_deref(), mask_record.as_ref(), post, &self.obj());
            drop(guard);
            if let Some(msg) = msg {
                let _ = self.obj().post_message(msg);
            }
            if let Some(e) = log_error.or(error) {
                gst::element_imp_error!(self, gst::StreamError::Failed, ["frame {}: {}", seq, e]);
                return Err(gst::FlowError::Error);
            }
            match outcome {
                Outcome::Keep => Ok(gst::FlowSuccess::Ok),
                Outcome::Drop => Ok(gst_base::BASE_TRANSFORM_FLOW_DROPPED),
            }
        }
    }
}
