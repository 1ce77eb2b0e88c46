//! dm-view: pinhole camera models and a deterministic CPU z-buffer renderer that
//! draws particles as lit sphere impostors ("splats").
//!
//! Used by the synthetic data generator to produce sensor-like images (RGB, depth,
//! label masks) and to draw preview images of simulations.
//!
//! Conventions:
//! - Cameras use OpenCV axes: x right, y down, z forward (optical axis).
//! - Pixel `(x, y)` covers `[x, x+1) x [y, y+1)` in image coordinates, so its centre
//!   is at `(x + 0.5, y + 0.5)`; `project` returns continuous image coordinates.
//! - Depth is the z coordinate in camera space (metres), not the ray length.
//! - Colours are plain `[0, 1]` display values; no gamma handling is applied.

mod camera;
pub mod chart;
mod error;
mod frame;
mod imaging;
mod render;

pub use camera::{Camera, NEAR_PLANE, orbit_cameras};
pub use error::ViewError;
pub use frame::Frame;
pub use imaging::{add_sensor_noise, side_by_side};
pub use render::{BAND_HEIGHT, FloorPlane, RenderOptions, Splat, render};
