use image::{GrayImage, ImageBuffer, Luma, RgbImage};
use nalgebra::Point3;

use crate::Camera;

/// Rendered sensor images, row-major (`index = y * width + x`).
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// Linear-in-value colours, nominally `[0, 1]` (not clamped).
    pub rgb: Vec<[f32; 3]>,
    /// Optical-axis depth in metres; `f32::INFINITY` where nothing was hit.
    pub depth: Vec<f32>,
    /// 0 = background / floor, otherwise the label of the visible splat.
    pub label: Vec<u8>,
    /// Index into the rendered splat slice; `u32::MAX` where no splat is visible.
    pub splat_index: Vec<u32>,
}

impl Frame {
    /// A frame with nothing drawn: black, infinite depth, label 0, no splat.
    pub fn empty(width: u32, height: u32) -> Frame {
        Frame::with_background(width, height, [0.0; 3])
    }

    /// A frame with nothing drawn over a uniform `background` colour.
    pub fn with_background(width: u32, height: u32, background: [f32; 3]) -> Frame {
        let pixel_count = width as usize * height as usize;
        Frame {
            width,
            height,
            rgb: vec![background; pixel_count],
            depth: vec![f32::INFINITY; pixel_count],
            label: vec![0; pixel_count],
            splat_index: vec![u32::MAX; pixel_count],
        }
    }

    /// Buffer index of pixel `(x, y)`, or `None` outside the image.
    pub fn pixel_index(&self, x: u32, y: u32) -> Option<usize> {
        (x < self.width && y < self.height).then(|| y as usize * self.width as usize + x as usize)
    }

    /// Depth at pixel `(x, y)` (`None` outside the image).
    pub fn depth_at(&self, x: u32, y: u32) -> Option<f32> {
        self.pixel_index(x, y)
            .and_then(|i| self.depth.get(i).copied())
    }

    /// 8-bit RGB image; values are clamped to `[0, 1]` and rounded.
    pub fn to_rgb8(&self) -> RgbImage {
        let bytes = self
            .rgb
            .iter()
            .flat_map(|pixel| pixel.map(unit_to_u8))
            .collect::<Vec<u8>>();
        RgbImage::from_raw(self.width, self.height, bytes)
            .unwrap_or_else(|| RgbImage::new(self.width, self.height))
    }

    /// Binary mask (255 where `label` is visible, else 0). `mask(0)` is the background
    /// and floor.
    pub fn mask(&self, label: u8) -> GrayImage {
        let bytes = self
            .label
            .iter()
            .map(|&l| if l == label { 255 } else { 0 })
            .collect::<Vec<u8>>();
        GrayImage::from_raw(self.width, self.height, bytes)
            .unwrap_or_else(|| GrayImage::new(self.width, self.height))
    }

    /// Depth as 16-bit millimetres, the usual depth-sensor PNG format: 0 where empty,
    /// saturating at 65535 (65.5 m).
    pub fn depth_to_u16_mm(&self) -> ImageBuffer<Luma<u16>, Vec<u16>> {
        let values = self
            .depth
            .iter()
            .map(|&d| {
                if d.is_finite() && d > 0.0 {
                    (d * 1000.0).round().min(f32::from(u16::MAX)) as u16
                } else {
                    0
                }
            })
            .collect::<Vec<u16>>();
        ImageBuffer::from_raw(self.width, self.height, values)
            .unwrap_or_else(|| ImageBuffer::new(self.width, self.height))
    }

    /// Whether `p_world` lies on the visible surface: it projects into the image and the
    /// rendered depth at its pixel (the pixel containing `(u, v)`) is within
    /// `tolerance_m` of its depth. Empty pixels (infinite depth) never match.
    ///
    /// For a splat *centre* the rendered surface is about `radius` nearer than the
    /// centre, so use `tolerance_m >= radius` (or [`Frame::visible_splats`]).
    pub fn is_visible(&self, camera: &Camera, p_world: &Point3<f64>, tolerance_m: f64) -> bool {
        self.rendered_depth_at_projection(camera, p_world)
            .is_some_and(|(rendered, z)| (rendered - z).abs() <= tolerance_m)
    }

    /// Whether nothing rendered occludes `p_world`: it projects into the image and the
    /// rendered depth at its pixel is not nearer than `z(p) - tolerance_m`. Unlike
    /// [`Frame::is_visible`] this is true for points floating in empty space.
    pub fn is_unoccluded(&self, camera: &Camera, p_world: &Point3<f64>, tolerance_m: f64) -> bool {
        self.rendered_depth_at_projection(camera, p_world)
            .is_some_and(|(rendered, z)| rendered >= z - tolerance_m)
    }

    /// `visible[i]` is true when splat `i` (of `splat_count`) owns at least one pixel.
    pub fn visible_splats(&self, splat_count: usize) -> Vec<bool> {
        let mut visible = vec![false; splat_count];
        for &index in &self.splat_index {
            if let Some(flag) = visible.get_mut(index as usize) {
                *flag = true;
            }
        }
        visible
    }

    fn rendered_depth_at_projection(
        &self,
        camera: &Camera,
        p_world: &Point3<f64>,
    ) -> Option<(f64, f64)> {
        let (u, v, z) = camera.project(p_world)?;
        if !(u >= 0.0 && v >= 0.0 && u < f64::from(self.width) && v < f64::from(self.height)) {
            return None;
        }
        let rendered = self.depth_at(u.floor() as u32, v.floor() as u32)?;
        Some((f64::from(rendered), z))
    }
}

fn unit_to_u8(value: f32) -> u8 {
    // NaN maps to 0 via the saturating cast.
    (value.clamp(0.0, 1.0) * 255.0).round() as u8
}
