//! `faultcam._faultcam`: the Python extension module behind the `faultcam` package
//! (python/faultcam/__init__.py wraps it).
//!
//! `Chain.apply` takes a C-contiguous numpy array — uint8 (H, W), (H, W, 1) or (H, W, 3) RGB, or
//! uint16 (H, W) / (H, W, 1) — and a frame index, copies it into a reused faultcam frame, runs
//! the chain exactly as `faultcam apply` does for the file with that index (same seed: same
//! bytes), and writes the result into a new array of the same shape and dtype. The GIL is
//! released while the pixels are copied and the chain runs.

use faultcam::control::{Controller, LogEvent};
use faultcam::faults::{ParamKind, Scale, registry};
use faultcam::gtlog::{FrameRecord, FrameStatus};
use faultcam::schedule::{TriggerOptions, controllers_from_config};
use faultcam::{Chain, FaultConfig, FaultError, Frame, FrameData, FrameReport, Outcome, PixelFormat};
use numpy::{PyArrayDescrMethods, PyArrayDyn, PyArrayMethods, PyUntypedArray, PyUntypedArrayMethods};
use pyo3::exceptions::{PyRuntimeError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::sync::Mutex;

const ACCEPTED: &str = "accepted: uint8 arrays of shape (H, W), (H, W, 1) (grey) or (H, W, 3) (RGB), \
                        uint16 arrays of shape (H, W) or (H, W, 1) (16-bit grey), C-contiguous";

struct Inner {
    chain: Chain,
    report: FrameReport,
    /// allocation: once per image size/format (the packed copy the chain works on).
    frame: Option<Frame>,
    /// The campaign timeline (`timeline=True`).
    timeline: Option<Timeline>,
}

/// The config's campaign timeline (`[[events]]`, `[triggers]` without a serial port), run as
/// `faultcam run` runs it on a `files:` source at `fps`: frame `seq` has stream time
/// `seq / fps`. Frame indices may come in any order: a jump forward steps the timeline through
/// the skipped frames, a jump back rebuilds chain and timeline from the config and replays them
/// from frame 0 (cost: the controller's steps, no pixels), so every index gets the effect
/// states of a sequential run.
struct Timeline {
    cfg: FaultConfig,
    controllers: Vec<Box<dyn Controller>>,
    /// The frame index the timeline expects next.
    next: u64,
    fps: f64,
    events: Vec<LogEvent>,
}

impl Timeline {
    fn t_ns(&self, seq: u64) -> u64 {
        (seq as f64 * 1e9 / self.fps).round() as u64
    }

    fn controllers(cfg: &FaultConfig) -> Result<Vec<Box<dyn Controller>>, String> {
        let opts = TriggerOptions { no_serial: true, ..TriggerOptions::default() };
        controllers_from_config(cfg, &opts).map_err(|e| e.to_string())
    }

    /// Bring the timeline (and the chain's effect states) to just before frame `seq`.
    fn seek(&mut self, seq: u64, chain: &mut Chain) -> Result<(), String> {
        if seq < self.next {
            *chain = Chain::from_config(&self.cfg).map_err(|e| e.to_string())?;
            self.controllers = Self::controllers(&self.cfg)?;
            self.next = 0;
        }
        while self.next < seq {
            let (s, t) = (self.next, self.t_ns(self.next));
            for c in &mut self.controllers {
                c.before_frame(s, t, chain, &mut self.events).map_err(|e| format!("frame {s}: {e:#}"))?;
                c.after_frame(s, t, FrameStatus::Delivered, &mut self.events);
            }
            self.next += 1;
        }
        // Events of the skipped frames are not this frame's.
        self.events.clear();
        Ok(())
    }
}

/// A fault chain loaded from a faultcam fault config (TOML).
#[pyclass(name = "Chain", module = "faultcam._faultcam")]
struct PyChain {
    inner: Mutex<Inner>,
    seed: u64,
    origin: String,
    names: Vec<&'static str>,
}

/// Shape and format of an input array, or an error naming what is accepted.
fn layout(arr: &Bound<'_, PyUntypedArray>) -> PyResult<(u32, u32, PixelFormat)> {
    let dims = arr.shape();
    // As Python prints it: (8, 8, 4), (8,).
    let shape = match dims {
        [d] => format!("({d},)"),
        _ => format!("({})", dims.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", ")),
    };
    let dtype = arr.dtype();
    let is_u8 = dtype.is_equiv_to(&numpy::dtype::<u8>(arr.py()));
    let is_u16 = dtype.is_equiv_to(&numpy::dtype::<u16>(arr.py()));
    if !is_u8 && !is_u16 {
        return Err(PyTypeError::new_err(format!("image dtype {dtype} is not accepted; {ACCEPTED}")));
    }
    let (h, w, c) = match dims {
        [h, w] => (*h, *w, 1),
        [h, w, c] => (*h, *w, *c),
        _ => return Err(PyValueError::new_err(format!("image shape {shape} is not accepted; {ACCEPTED}"))),
    };
    let format = match (is_u16, c) {
        (false, 1) => PixelFormat::Mono8,
        (false, 3) => PixelFormat::Rgb8,
        (true, 1) => PixelFormat::Mono16,
        _ => {
            return Err(PyValueError::new_err(format!(
                "image shape {shape} with dtype {dtype} is not accepted; {ACCEPTED}"
            )));
        }
    };
    if h == 0 || w == 0 || h > u32::MAX as usize || w > u32::MAX as usize {
        return Err(PyValueError::new_err(format!("image shape {shape}: width and height must be 1..=4294967295")));
    }
    if !arr.is_c_contiguous() {
        return Err(PyValueError::new_err(format!(
            "image is not C-contiguous; {ACCEPTED} (use numpy.ascontiguousarray)"
        )));
    }
    Ok((w as u32, h as u32, format))
}

/// Input or output samples (borrowed from numpy arrays).
enum Samples<'a> {
    U8(&'a [u8]),
    U16(&'a [u16]),
}
enum SamplesMut<'a> {
    U8(&'a mut [u8]),
    U16(&'a mut [u16]),
}

/// A frame's log status from the chain's result, with the error text when it failed.
fn status_of(result: &Result<Outcome, FaultError>) -> (FrameStatus, Option<String>) {
    match result {
        Ok(Outcome::Keep) => (FrameStatus::Delivered, None),
        Ok(Outcome::Drop) => (FrameStatus::DroppedByFault, None),
        Err(e) => (FrameStatus::Failed, Some(e.to_string())),
    }
}

impl Inner {
    /// Copy in, run the chain, copy out. Runs without the GIL.
    fn run(
        &mut self,
        w: u32,
        h: u32,
        format: PixelFormat,
        seq: u64,
        src: Samples<'_>,
        dst: SamplesMut<'_>,
    ) -> Result<(bool, String), String> {
        let reuse = self.frame.as_ref().is_some_and(|f| f.width == w && f.height == h && f.format == format);
        if !reuse {
            self.frame = Some(Frame::new(w, h, format).map_err(|e| e.to_string())?);
        }
        let frame = self.frame.as_mut().expect("set above");
        match (&mut frame.data, src) {
            (FrameData::U8(d), Samples::U8(s)) => d.copy_from_slice(s),
            (FrameData::U16(d), Samples::U16(s)) => d.copy_from_slice(s),
            _ => return Err("internal: sample type mismatch".into()),
        }
        frame.seq = seq;
        // As `faultcam apply`: files carry no timestamps; with the timeline, as `faultcam run` on
        // a `files:` source: seq / fps.
        frame.pts_ns = 0;
        if let Some(tl) = self.timeline.as_mut() {
            tl.seek(seq, &mut self.chain)?;
            frame.pts_ns = tl.t_ns(seq);
            for c in &mut tl.controllers {
                c.before_frame(seq, frame.pts_ns, &mut self.chain, &mut tl.events)
                    .map_err(|e| format!("frame {seq}: {e:#}"))?;
            }
        }
        let result = self.chain.apply(frame, &mut self.report);
        let (status, error) = status_of(&result);
        let kept = status == FrameStatus::Delivered;
        let pts_ns = frame.pts_ns;
        let mut events = Vec::new();
        if let Some(tl) = self.timeline.as_mut() {
            for c in &mut tl.controllers {
                c.after_frame(seq, pts_ns, status, &mut tl.events);
            }
            tl.next = seq + 1;
            events = std::mem::take(&mut tl.events); // allocation: only with campaign events
        }
        if kept {
            if frame.width != w || frame.height != h || frame.format != format {
                return Err(format!(
                    "the chain returned a {}x{} {} frame for a {w}x{h} {format} input",
                    frame.width, frame.height, frame.format
                ));
            }
            match (&frame.data, dst) {
                (FrameData::U8(d), SamplesMut::U8(o)) => o.copy_from_slice(d),
                (FrameData::U16(d), SamplesMut::U16(o)) => o.copy_from_slice(d),
                _ => return Err("internal: sample type mismatch".into()),
            }
        }
        let mut rec = FrameRecord::from_report(seq, pts_ns, &self.report);
        rec.status = status;
        rec.error = error.as_deref();
        let mut json = serde_json::to_string(&rec).map_err(|e| e.to_string())?;
        if self.timeline.is_some() {
            // The campaign events logged before this frame (the log's `event` lines).
            json.pop();
            json.push_str(",\"events\":");
            json.push_str(&serde_json::to_string(&events).map_err(|e| e.to_string())?);
            json.push('}');
        }
        if let Some(e) = error {
            return Err(format!("frame {seq}: {e}"));
        }
        Ok((kept, json))
    }
}

#[pymethods]
impl PyChain {
    /// Load a fault config (TOML, as `faultcam apply --faults`); `seed` overrides its `seed`.
    #[staticmethod]
    #[pyo3(signature = (path, seed=None, timeline=false, fps=30.0))]
    fn from_toml(path: std::path::PathBuf, seed: Option<u64>, timeline: bool, fps: f64) -> PyResult<PyChain> {
        let mut cfg = FaultConfig::load(&path).map_err(|e| PyValueError::new_err(e.to_string()))?;
        if let Some(s) = seed {
            cfg.seed = s;
        }
        let chain = Chain::from_config(&cfg).map_err(|e| PyValueError::new_err(format!("{}: {e}", path.display())))?;
        let names = chain.entries().iter().filter(|e| e.enabled).map(|e| e.name()).collect();
        let timeline = if timeline {
            if !(fps.is_finite() && fps > 0.0 && fps <= 1e6) {
                return Err(PyValueError::new_err(format!("fps {fps} is not accepted; accepted: 0 < fps <= 1e6")));
            }
            let controllers =
                Timeline::controllers(&cfg).map_err(|e| PyValueError::new_err(format!("{}: {e}", path.display())))?;
            Some(Timeline { cfg: cfg.clone(), controllers, next: 0, fps, events: Vec::new() })
        } else {
            None
        };
        Ok(PyChain {
            seed: cfg.seed,
            origin: path.display().to_string(),
            names,
            inner: Mutex::new(Inner { chain, report: FrameReport::default(), frame: None, timeline }),
        })
    }

    /// Campaign seed in use.
    #[getter]
    fn seed(&self) -> u64 {
        self.seed
    }

    /// Enabled effects in application (physical) order.
    #[getter]
    fn effects(&self) -> Vec<&'static str> {
        self.names.clone()
    }

    /// Apply the chain to `image` as frame `frame_index`. Returns (output array or None when an
    /// effect dropped the frame, the ground-truth record as a JSON string).
    fn apply_json<'py>(
        &self,
        py: Python<'py>,
        image: &Bound<'py, PyUntypedArray>,
        frame_index: u64,
    ) -> PyResult<(Option<Bound<'py, PyUntypedArray>>, String)> {
        let (w, h, format) = layout(image)?;
        let shape = image.shape().to_vec();
        let result = if format == PixelFormat::Mono16 {
            let inp = image.cast::<PyArrayDyn<u16>>()?.readonly();
            let out = unsafe { PyArrayDyn::<u16>::new(py, shape, false) };
            let mut wr = out.readwrite();
            let src = inp.as_slice().map_err(|e| PyValueError::new_err(e.to_string()))?;
            let dst = wr.as_slice_mut().map_err(|e| PyValueError::new_err(e.to_string()))?;
            let r = py.detach(|| {
                let mut g = self.inner.lock().map_err(|_| "an earlier call panicked".to_string())?;
                g.run(w, h, format, frame_index, Samples::U16(src), SamplesMut::U16(dst))
            });
            drop(wr);
            r.map(|(kept, json)| (kept.then(|| out.into_any().cast_into::<PyUntypedArray>().expect("array")), json))
        } else {
            let inp = image.cast::<PyArrayDyn<u8>>()?.readonly();
            let out = unsafe { PyArrayDyn::<u8>::new(py, shape, false) };
            let mut wr = out.readwrite();
            let src = inp.as_slice().map_err(|e| PyValueError::new_err(e.to_string()))?;
            let dst = wr.as_slice_mut().map_err(|e| PyValueError::new_err(e.to_string()))?;
            let r = py.detach(|| {
                let mut g = self.inner.lock().map_err(|_| "an earlier call panicked".to_string())?;
                g.run(w, h, format, frame_index, Samples::U8(src), SamplesMut::U8(dst))
            });
            drop(wr);
            r.map(|(kept, json)| (kept.then(|| out.into_any().cast_into::<PyUntypedArray>().expect("array")), json))
        };
        result.map_err(PyRuntimeError::new_err)
    }

    /// Frames effects still hold at the end of a stream (`reorder`), passed through the later
    /// effects: a list of (output array or None when a later effect dropped it, the record as a
    /// JSON string). Call once after the last `apply`, as `faultcam run` does at the end.
    fn drain_json<'py>(&self, py: Python<'py>) -> PyResult<Vec<(Option<Bound<'py, PyUntypedArray>>, String)>> {
        let mut out = Vec::new();
        loop {
            let next = {
                let mut g = self.inner.lock().map_err(|_| PyRuntimeError::new_err("an earlier call panicked"))?;
                let g = &mut *g;
                g.chain.drain_next(&mut g.report).map(|(frame, result)| {
                    let (status, error) = status_of(&result);
                    let mut rec = FrameRecord::from_report(frame.seq, frame.pts_ns, &g.report);
                    rec.status = status;
                    rec.error = error.as_deref();
                    let json = serde_json::to_string(&rec).unwrap_or_default();
                    (frame, status, json)
                })
            };
            let Some((frame, status, json)) = next else { return Ok(out) };
            let arr = if status != FrameStatus::Delivered {
                None
            } else {
                let (h, w) = (frame.height as usize, frame.width as usize);
                let shape: Vec<usize> = if frame.format == PixelFormat::Rgb8 { vec![h, w, 3] } else { vec![h, w] };
                let row = frame.row_len();
                let a = match &frame.data {
                    FrameData::U8(d) => {
                        let v: Vec<u8> =
                            d.chunks(frame.stride).take(h).flat_map(|r| r[..row].iter().copied()).collect();
                        numpy::PyArray1::from_vec(py, v).reshape(shape)?.into_any()
                    }
                    FrameData::U16(d) => {
                        let v: Vec<u16> =
                            d.chunks(frame.stride).take(h).flat_map(|r| r[..row].iter().copied()).collect();
                        numpy::PyArray1::from_vec(py, v).reshape(shape)?.into_any()
                    }
                };
                Some(a.cast_into::<PyUntypedArray>().expect("array"))
            };
            out.push((arr, json));
        }
    }

    fn __repr__(&self) -> String {
        format!("faultcam.Chain({:?}, seed={}, effects={:?})", self.origin, self.seed, self.names)
    }
}

/// Every effect with its stage, model and parameter specs (units, ranges, defaults).
#[pyfunction]
fn effects(py: Python<'_>) -> PyResult<Bound<'_, PyList>> {
    let out = PyList::empty(py);
    for r in registry::all() {
        let info = r.info;
        let d = PyDict::new(py);
        d.set_item("name", info.name)?;
        d.set_item("stage", info.stage.name())?;
        d.set_item("summary", info.summary)?;
        d.set_item("model", info.model)?;
        d.set_item("formats", info.formats.iter().map(|f| f.name()).collect::<Vec<_>>())?;
        let params = PyList::empty(py);
        for p in info.params {
            let q = PyDict::new(py);
            q.set_item("name", p.name)?;
            q.set_item("unit", p.unit)?;
            q.set_item("min", p.min)?;
            q.set_item("max", p.max)?;
            q.set_item("default", p.default)?;
            let (kind, choices): (&str, Option<Vec<&str>>) = match p.kind {
                ParamKind::Float => ("float", None),
                ParamKind::Int => ("int", None),
                ParamKind::Bool => ("bool", None),
                ParamKind::Choice(c) => ("choice", Some(c.to_vec())),
            };
            q.set_item("kind", kind)?;
            q.set_item("choices", choices)?;
            q.set_item("scale", if p.scale == Scale::Log { "log" } else { "linear" })?;
            q.set_item("canonical", p.canonical)?;
            q.set_item("range", p.range_text())?;
            q.set_item("doc", p.doc)?;
            params.append(q)?;
        }
        d.set_item("params", params)?;
        out.append(d)?;
    }
    Ok(out)
}

#[pymodule]
fn _faultcam(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyChain>()?;
    m.add_function(wrap_pyfunction!(effects, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
