//! GStreamer plugin `faultcam`: the faultcam fault chain as an in-place video filter.
//!
//! ```text
//! GST_PLUGIN_PATH=target/debug gst-launch-1.0 videotestsrc num-buffers=30 ! \
//!   video/x-raw,format=GRAY8,width=320,height=240 ! faultcam config=faults.toml seed=7 ! fakesink
//! ```
//!
//! See [`FaultCamFilter`] for the element's properties, caps, timeline and messages.

use gst::glib;

mod filter;

pub use filter::{FaultCamFilter, MESSAGE_NAME};

/// Register the `faultcam` element with `plugin` (or statically with `None`, for tests and
/// applications that link the crate).
pub fn register(plugin: Option<&gst::Plugin>) -> Result<(), glib::BoolError> {
    filter::register(plugin)
}

fn plugin_init(plugin: &gst::Plugin) -> Result<(), glib::BoolError> {
    register(Some(plugin))
}

gst::plugin_define!(
    faultcam,
    env!("CARGO_PKG_DESCRIPTION"),
    plugin_init,
    env!("CARGO_PKG_VERSION"),
    // GStreamer's license names: the crate is MIT OR Apache-2.0.
    "MIT/X11",
    env!("CARGO_PKG_NAME"),
    env!("CARGO_PKG_NAME"),
    "faultcam (this repository)"
);
