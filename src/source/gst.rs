//! `gst:PIPELINE` source: any GStreamer pipeline that ends in an `appsink`.
//!
//! ```text
//! gst:videotestsrc num-buffers=30 ! video/x-raw,format=GRAY8,width=320,height=240 ! appsink
//! gst:filesrc location=x.mkv ! decodebin ! videoconvert ! appsink
//! gst:aravissrc camera-name=Fake_1 ! videoconvert ! appsink
//! ```
//!
//! * The frames are taken from the appsink named `faultcam` if there is one, otherwise from
//!   the last appsink of the description.
//! * The appsink is asked for raw video in `GRAY8`, `GRAY16_LE` or `RGB` (→ `Mono8`, `Mono16`,
//!   `Rgb8`); upstream chooses among them. If upstream produces something else, add
//!   `videoconvert` before the appsink. The negotiated caps are reported by `describe()`.
//! * Rows are copied out of the (possibly padded, e.g. 4-byte aligned) GStreamer buffer into
//!   pooled, tightly packed frames; `pts_ns` is the buffer timestamp.
//! * End of stream (EOS) ends the source; a bus error becomes a fatal error naming the element.
//! * If the appsink has no `max-buffers` set, it is limited to 4 so a fast decoder blocks
//!   instead of queueing the whole file (nothing is dropped: `drop` stays as set).

use super::{Source, SourceError};
use crate::frame::{Frame, PixelFormat};
use crate::pipeline::pool::{FramePool, copy_rows_into};
use gstreamer as gst;
use gstreamer::prelude::*;
use gstreamer_app as gst_app;
use gstreamer_video as gst_video;
use gstreamer_video::prelude::*;
use std::time::Duration;

/// How long `open` waits for the first frame to learn the negotiated caps.
const PREROLL_TIMEOUT: Duration = Duration::from_secs(10);
/// Poll interval while waiting for a sample (the bus is checked between polls).
const PULL_POLL: Duration = Duration::from_millis(100);

/// A running GStreamer pipeline feeding frames from its appsink.
pub struct GstSource {
    desc: String,
    pipeline: gst::Pipeline,
    appsink: gst_app::AppSink,
    bus: gst::Bus,
    caps: Option<gst::Caps>,
    info: Option<gst_video::VideoInfo>,
    format: PixelFormat,
    pool: FramePool,
    seq: u64,
    eos: bool,
    /// A bus error seen while frames the pipeline made before it still wait in the appsink:
    /// those are delivered first, then the error ends the stream.
    pending_error: Option<String>,
}

/// Text of the first error message on the bus, naming the element that posted it.
pub(crate) fn bus_error(bus: &gst::Bus, timeout: Option<gst::ClockTime>) -> Option<String> {
    let msg = match timeout {
        Some(t) => bus.timed_pop_filtered(t, &[gst::MessageType::Error])?,
        None => bus.pop_filtered(&[gst::MessageType::Error])?,
    };
    match msg.view() {
        gst::MessageView::Error(e) => {
            let element = e.src().map(|s| s.path_string().to_string()).unwrap_or_else(|| "pipeline".into());
            let debug = e.debug().map(|d| format!(" ({d})")).unwrap_or_default();
            Some(format!("element {element}: {}{debug}", e.error()))
        }
        _ => None,
    }
}

/// Parse a description into a pipeline (errors name the problem as GStreamer reports it).
pub(crate) fn parse_pipeline(desc: &str) -> Result<gst::Pipeline, String> {
    gst::init().map_err(|e| format!("cannot initialise GStreamer: {e}"))?;
    let element = gst::parse::launch(desc).map_err(|e| format!("cannot parse the pipeline: {e}"))?;
    element
        .downcast::<gst::Pipeline>()
        .map_err(|_| "the description must contain a whole pipeline (several elements linked with !)".to_string())
}

/// Elements of `pipeline` made by `factory`, in description order (a bin keeps its
/// children newest first).
pub(crate) fn elements_by_factory(pipeline: &gst::Pipeline, factory: &str) -> Vec<gst::Element> {
    let mut v: Vec<gst::Element> =
        pipeline.children().into_iter().filter(|e| e.factory().is_some_and(|f| f.name() == factory)).collect();
    v.reverse();
    v
}

fn map_format(f: gst_video::VideoFormat) -> Option<PixelFormat> {
    match f {
        gst_video::VideoFormat::Gray8 => Some(PixelFormat::Mono8),
        gst_video::VideoFormat::Gray16Le => Some(PixelFormat::Mono16),
        gst_video::VideoFormat::Rgb => Some(PixelFormat::Rgb8),
        _ => None,
    }
}

impl GstSource {
    /// Build and start the pipeline, and wait (up to 10 s) for the first frame so the
    /// negotiated format is known.
    /// `uri` is `gst:PIPELINE` (or just the pipeline description).
    pub fn open(uri: &str) -> Result<GstSource, SourceError> {
        let desc = uri.strip_prefix("gst:").unwrap_or(uri).trim();
        let uri = format!("gst:{desc}");
        let bad = |reason: String| SourceError::BadUri { uri: uri.clone(), reason };
        let pipeline = parse_pipeline(desc).map_err(bad)?;
        let sinks = elements_by_factory(&pipeline, "appsink");
        let chosen = pipeline
            .by_name("faultcam")
            .filter(|e| e.factory().is_some_and(|f| f.name() == "appsink"))
            .or_else(|| sinks.last().cloned())
            .ok_or_else(|| bad("the pipeline must end in an appsink (e.g. '... ! videoconvert ! appsink')".into()))?;
        let appsink =
            chosen.downcast::<gst_app::AppSink>().map_err(|_| bad("the appsink element is not an AppSink".into()))?;
        let caps = gst_video::VideoCapsBuilder::new()
            .format_list([gst_video::VideoFormat::Gray8, gst_video::VideoFormat::Gray16Le, gst_video::VideoFormat::Rgb])
            .build();
        appsink.set_caps(Some(&caps));
        if appsink.max_buffers() == 0 {
            appsink.set_max_buffers(4);
        }
        let bus = pipeline.bus().ok_or_else(|| bad("the pipeline has no bus".into()))?;
        let mut src = GstSource {
            desc: desc.to_string(),
            pipeline,
            appsink,
            bus,
            caps: None,
            info: None,
            format: PixelFormat::Mono8,
            pool: FramePool::new(8),
            seq: 0,
            eos: false,
            pending_error: None,
        };
        if src.pipeline.set_state(gst::State::Playing).is_err() {
            let why = bus_error(&src.bus, Some(gst::ClockTime::from_seconds(1)))
                .unwrap_or_else(|| "the pipeline refused to start".into());
            return Err(src.fatal(why));
        }
        // The preroll sample is also the first sample `pull_sample` returns.
        match src.appsink.try_pull_preroll(gst::ClockTime::from_nseconds(PREROLL_TIMEOUT.as_nanos() as u64)) {
            Some(sample) => {
                if let Some(caps) = sample.caps() {
                    src.set_caps(caps)?;
                }
            }
            None => {
                if let Some(why) = bus_error(&src.bus, None) {
                    return Err(src.fatal(why));
                }
                // EOS before any frame, or a slow live source: caps are reported later.
            }
        }
        Ok(src)
    }

    fn fatal(&self, reason: String) -> SourceError {
        SourceError::Fatal { uri: format!("gst:{}", self.desc), reason }
    }

    fn set_caps(&mut self, caps: &gst::CapsRef) -> Result<(), SourceError> {
        if self.caps.as_ref().is_some_and(|c| c.as_ref() == caps) {
            return Ok(());
        }
        let info = gst_video::VideoInfo::from_caps(caps)
            .map_err(|e| self.fatal(format!("cannot read the negotiated caps {caps}: {e}")))?;
        let format = map_format(info.format()).ok_or_else(|| {
            self.fatal(format!(
                "negotiated format {:?} is not one of GRAY8, GRAY16_LE, RGB; add videoconvert before the appsink",
                info.format()
            ))
        })?;
        // A negotiated size over the image limits stops the stream before a frame is allocated.
        crate::limits::ImageLimits::current()
            .check(
                &format!("the negotiated caps {caps}"),
                info.width(),
                info.height(),
                (format.channels() * format.bytes_per_sample()) as u64,
            )
            .map_err(|e| self.fatal(e))?;
        self.format = format;
        self.info = Some(info);
        self.caps = Some(caps.to_owned());
        Ok(())
    }

    /// The negotiated caps, once known.
    pub fn caps(&self) -> Option<&gst::Caps> {
        self.caps.as_ref()
    }

    fn frame_from_sample(&mut self, sample: &gst::Sample) -> Result<Frame, SourceError> {
        let caps = sample.caps().ok_or_else(|| self.fatal("sample without caps".into()))?;
        self.set_caps(caps)?;
        let buffer = sample.buffer().ok_or_else(|| self.fatal("sample without a buffer".into()))?;
        let info = self.info.as_ref().ok_or_else(|| self.fatal("no video info".into()))?;
        let vf = gst_video::VideoFrameRef::from_buffer_ref_readable(buffer, info)
            .map_err(|e| self.fatal(format!("cannot map a video buffer: {e}")))?;
        let (w, h) = (vf.width(), vf.height());
        let stride = vf.plane_stride()[0];
        let data = vf.plane_data(0).map_err(|e| self.fatal(format!("cannot read plane 0: {e}")))?;
        if stride <= 0 {
            return Err(self.fatal(format!("unsupported stride {stride}")));
        }
        let mut frame = self.pool.take(w, h, self.format).map_err(|e| self.fatal(e.to_string()))?;
        copy_rows_into(&mut frame, data, stride as usize).map_err(|e| self.fatal(e.to_string()))?;
        frame.seq = self.seq;
        frame.pts_ns = buffer.pts().map(|t| t.nseconds()).unwrap_or(0);
        self.seq += 1;
        Ok(frame)
    }
}

impl Source for GstSource {
    fn describe(&self) -> String {
        match &self.caps {
            Some(c) => format!("gst:{} (negotiated {c})", self.desc),
            None => format!("gst:{} (caps not negotiated yet)", self.desc),
        }
    }

    fn next_frame(&mut self) -> Result<Option<Frame>, SourceError> {
        if self.eos {
            return Ok(None);
        }
        loop {
            if self.pending_error.is_none() {
                self.pending_error = bus_error(&self.bus, None);
            }
            if self.pending_error.is_some() {
                // Frames that reached the appsink before the error are not lost with it.
                if let Some(sample) = self.appsink.try_pull_sample(gst::ClockTime::ZERO) {
                    return self.frame_from_sample(&sample).map(Some);
                }
                self.eos = true;
                let why = self.pending_error.take().unwrap_or_default();
                return Err(self.fatal(why));
            }
            match self.appsink.try_pull_sample(gst::ClockTime::from_nseconds(PULL_POLL.as_nanos() as u64)) {
                Some(sample) => return self.frame_from_sample(&sample).map(Some),
                None => {
                    if self.appsink.is_eos() {
                        if let Some(why) = bus_error(&self.bus, None) {
                            self.eos = true;
                            return Err(self.fatal(why));
                        }
                        self.eos = true;
                        return Ok(None);
                    }
                }
            }
        }
    }

    fn recycle(&mut self, frame: Frame) {
        self.pool.give(frame);
    }
}

impl Drop for GstSource {
    fn drop(&mut self) {
        let _ = self.pipeline.set_state(gst::State::Null);
    }
}
