//! `gst:PIPELINE` sink: any GStreamer pipeline that starts with an `appsrc`.
//!
//! ```text
//! gst:appsrc ! videoconvert ! vp8enc ! webmmux ! filesink location=out.webm
//! gst:appsrc ! videoconvert ! jpegenc ! multifilesink location=out/%05d.jpg
//! gst:appsrc ! videoconvert ! video/x-raw,format=I420 ! rtpvrawpay ! udpsink host=127.0.0.1 port=5004
//! gst:appsrc ! videoconvert ! autovideosink
//! ```
//!
//! * Frames go into the appsrc named `faultcam` if there is one, otherwise into the first
//!   appsrc of the description.
//! * The caps are set from the first frame: `video/x-raw` `GRAY8` / `GRAY16_LE` / `RGB`
//!   (Mono8 / Mono16 / Rgb8; Bayer8 goes out as GRAY8), its width and height, framerate 0/1
//!   (variable). Later frames must keep that size and format.
//! * Buffers come from a GStreamer buffer pool (no allocation per frame once it has grown)
//!   and carry timestamps: the frame's `pts_ns` relative to the first frame, or, if the
//!   timestamps do not increase, a nominal 30 fps clock.
//! * The appsrc blocks when its queue is full (backpressure reaches the pipeline's queues, no
//!   frame is dropped). `finish` sends EOS and waits for it (or an error) on the bus, so
//!   files are complete when the run ends.

use super::{Sink, SinkError};
use crate::frame::{Frame, PixelFormat};
use crate::pipeline::pool::copy_rows_out;
use crate::source::gst::{bus_error, elements_by_factory, parse_pipeline};
use gstreamer as gst;
use gstreamer::prelude::*;
use gstreamer_app as gst_app;
use gstreamer_video as gst_video;
use gstreamer_video::prelude::*;

/// How long `finish` waits for EOS to reach the end of the pipeline.
const EOS_TIMEOUT_S: u64 = 60;
/// Nominal frame interval when frames carry no usable timestamps.
const NOMINAL_FRAME_NS: u64 = 33_333_333;

/// A running GStreamer pipeline fed through its appsrc.
pub struct GstSink {
    desc: String,
    pipeline: gst::Pipeline,
    appsrc: gst_app::AppSrc,
    bus: gst::Bus,
    shape: Option<(u32, u32, PixelFormat)>,
    info: Option<gst_video::VideoInfo>,
    pool: Option<gst::BufferPool>,
    first_pts: Option<u64>,
    last_pts: Option<u64>,
    synthetic: bool,
    frames: u64,
    finished: bool,
}

fn gst_format(f: PixelFormat) -> gst_video::VideoFormat {
    match f {
        PixelFormat::Mono8 | PixelFormat::Bayer8 => gst_video::VideoFormat::Gray8,
        PixelFormat::Mono16 => gst_video::VideoFormat::Gray16Le,
        PixelFormat::Rgb8 => gst_video::VideoFormat::Rgb,
    }
}

impl GstSink {
    /// Build the pipeline and start it (it waits in PLAYING for the first buffer).
    /// `uri` is `gst:PIPELINE` (or just the pipeline description).
    pub fn open(uri: &str) -> Result<GstSink, SinkError> {
        let desc = uri.strip_prefix("gst:").unwrap_or(uri).trim();
        let uri = format!("gst:{desc}");
        let bad = |reason: String| SinkError::BadUri { uri: uri.clone(), reason };
        let pipeline = parse_pipeline(desc).map_err(bad)?;
        let srcs = elements_by_factory(&pipeline, "appsrc");
        let chosen = pipeline
            .by_name("faultcam")
            .filter(|e| e.factory().is_some_and(|f| f.name() == "appsrc"))
            .or_else(|| srcs.first().cloned())
            .ok_or_else(|| bad("the pipeline must start with an appsrc (e.g. 'appsrc ! videoconvert ! ...')".into()))?;
        let appsrc =
            chosen.downcast::<gst_app::AppSrc>().map_err(|_| bad("the appsrc element is not an AppSrc".into()))?;
        appsrc.set_format(gst::Format::Time);
        appsrc.set_block(true);
        let bus = pipeline.bus().ok_or_else(|| bad("the pipeline has no bus".into()))?;
        let sink = GstSink {
            desc: desc.to_string(),
            pipeline,
            appsrc,
            bus,
            shape: None,
            info: None,
            pool: None,
            first_pts: None,
            last_pts: None,
            synthetic: false,
            frames: 0,
            finished: false,
        };
        if sink.pipeline.set_state(gst::State::Playing).is_err() {
            let why = bus_error(&sink.bus, Some(gst::ClockTime::from_seconds(1)))
                .unwrap_or_else(|| "the pipeline refused to start".into());
            return Err(sink.failed(why));
        }
        Ok(sink)
    }

    fn failed(&self, reason: String) -> SinkError {
        SinkError::Failed { uri: format!("gst:{}", self.desc), reason }
    }

    /// Set caps and a buffer pool from the first frame.
    fn configure(&mut self, frame: &Frame) -> Result<(), SinkError> {
        let shape = (frame.width, frame.height, frame.format);
        if let Some(s) = self.shape {
            if s != shape {
                return Err(self.failed(format!(
                    "frame {} is {}x{} {}, but the stream started as {}x{} {}; a gst sink carries one format",
                    frame.seq, frame.width, frame.height, frame.format, s.0, s.1, s.2
                )));
            }
            return Ok(());
        }
        let info = gst_video::VideoInfo::builder(gst_format(frame.format), frame.width, frame.height)
            .fps(gst::Fraction::new(0, 1))
            .build()
            .map_err(|e| {
                self.failed(format!("cannot describe {}x{} {}: {e}", frame.width, frame.height, frame.format))
            })?;
        let caps = info.to_caps().map_err(|e| self.failed(format!("cannot build caps: {e}")))?;
        self.appsrc.set_caps(Some(&caps));
        let pool = gst::BufferPool::new();
        let mut config = pool.config();
        config.set_params(Some(&caps), info.size() as u32, 2, 0);
        pool.set_config(config).map_err(|e| self.failed(format!("buffer pool: {e}")))?;
        pool.set_active(true).map_err(|e| self.failed(format!("buffer pool: {e}")))?;
        self.pool = Some(pool);
        self.info = Some(info);
        self.shape = Some(shape);
        Ok(())
    }

    fn timestamp(&mut self, pts_ns: u64) -> u64 {
        let first = *self.first_pts.get_or_insert(pts_ns);
        let rel = pts_ns.saturating_sub(first);
        let t = match self.last_pts {
            Some(last) if self.synthetic || rel <= last => {
                self.synthetic = true;
                self.frames * NOMINAL_FRAME_NS
            }
            _ => rel,
        };
        self.last_pts = Some(t);
        t
    }

    /// The pipeline's error, if one was posted, else a generic flow error text.
    fn flow_error(&self, flow: gst::FlowError) -> SinkError {
        match bus_error(&self.bus, Some(gst::ClockTime::from_mseconds(200))) {
            Some(why) => self.failed(why),
            None if matches!(flow, gst::FlowError::Flushing | gst::FlowError::Eos) => {
                SinkError::Closed { uri: format!("gst:{}", self.desc) }
            }
            None => self.failed(format!("pushing a buffer failed: {flow:?}")),
        }
    }
}

impl Sink for GstSink {
    fn describe(&self) -> String {
        match &self.info {
            Some(i) => format!("gst:{} ({}x{} {:?})", self.desc, i.width(), i.height(), i.format()),
            None => format!("gst:{} (caps from the first frame)", self.desc),
        }
    }

    fn write_frame(&mut self, frame: &Frame, _name: Option<&str>) -> Result<(), SinkError> {
        if let Some(why) = bus_error(&self.bus, None) {
            return Err(self.failed(why));
        }
        self.configure(frame)?;
        let pts = self.timestamp(frame.pts_ns);
        let (Some(pool), Some(info)) = (self.pool.as_ref(), self.info.as_ref()) else {
            return Err(self.failed("not configured".into()));
        };
        let buffer = pool.acquire_buffer(None).map_err(|e| self.failed(format!("buffer pool: {e:?}")))?;
        let mut vf = gst_video::VideoFrame::from_buffer_writable(buffer, info)
            .map_err(|_| self.failed("cannot map a pool buffer".into()))?;
        let stride = vf.plane_stride()[0] as usize;
        let plane = vf.plane_data_mut(0).map_err(|e| self.failed(format!("cannot write plane 0: {e}")))?;
        copy_rows_out(frame, plane, stride).map_err(|e| self.failed(e.to_string()))?;
        let mut buffer = vf.into_buffer();
        {
            let b = buffer.make_mut();
            b.set_pts(gst::ClockTime::from_nseconds(pts));
            b.set_offset(self.frames);
        }
        self.appsrc.push_buffer(buffer).map_err(|flow| self.flow_error(flow))?;
        self.frames += 1;
        Ok(())
    }

    fn finish(&mut self) -> Result<(), SinkError> {
        if self.finished {
            return Ok(());
        }
        self.finished = true;
        let result = match self.appsrc.end_of_stream() {
            Err(flow) => Err(self.flow_error(flow)),
            Ok(_) => {
                let msg = self.bus.timed_pop_filtered(
                    gst::ClockTime::from_seconds(EOS_TIMEOUT_S),
                    &[gst::MessageType::Eos, gst::MessageType::Error],
                );
                match msg {
                    None => Err(self.failed(format!("no EOS from the pipeline within {EOS_TIMEOUT_S} s"))),
                    Some(m) => match m.view() {
                        gst::MessageView::Eos(_) => Ok(()),
                        gst::MessageView::Error(e) => {
                            let element =
                                e.src().map(|s| s.path_string().to_string()).unwrap_or_else(|| "pipeline".into());
                            Err(self.failed(format!("element {element}: {}", e.error())))
                        }
                        _ => Ok(()),
                    },
                }
            }
        };
        let _ = self.pipeline.set_state(gst::State::Null);
        if let Some(p) = &self.pool {
            let _ = p.set_active(false);
        }
        result
    }
}

impl Drop for GstSink {
    fn drop(&mut self) {
        let _ = self.pipeline.set_state(gst::State::Null);
    }
}
