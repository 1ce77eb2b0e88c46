//! Writing a bundle so that the final directory appears complete or not at all.

use std::fs;
use std::path::{Path, PathBuf};

use image::{GrayImage, ImageBuffer, ImageFormat, Luma, RgbImage};

use crate::bundle::{
    BUNDLE_JSON, Bundle, DEFAULT_MESH_FILE, DEPTH_PNG_UNITS_PER_METRE, FirstFrameParticles,
    HAND_POINTS_FILE, HAND_VISIBILITY_FILE, INTERIOR_COLORS_FILE, INTERIOR_POINTS_FILE, ImageKind,
    OBJECT_MOTION_VALID_FILE, OBJECT_POINTS_FILE, OBJECT_VISIBILITY_FILE, PARTICLES_DIR,
    SURFACE_COLORS_FILE, SURFACE_POINTS_FILE, TRACKS_DIR, Tracks, VIEWS_DIR, image_path,
};
use crate::error::{BundleError, Result};
use crate::meta::{BundleMeta, remove_abandoned_temporaries, unique_sibling, write_json_atomic};
use crate::npy::write_npy_file;

/// Converts a depth in metres to the stored PNG value: millimetres rounded to
/// nearest, clamped to `1..=65535`; NaN, infinities and values <= 0 become 0
/// ("no measurement"). The lower clamp keeps a real sub-millimetre measurement
/// from turning into "no measurement".
pub fn depth_m_to_png_mm(depth_m: f32) -> u16 {
    if !(depth_m.is_finite() && depth_m > 0.0) {
        return 0;
    }
    // `as` saturates, and the clamp makes the range explicit.
    (depth_m * DEPTH_PNG_UNITS_PER_METRE)
        .round()
        .clamp(1.0, f32::from(u16::MAX)) as u16
}

/// Builds a bundle in a temporary sibling directory (`<final>.tmp-<pid>-<n>`) and
/// renames it into place in [`BundleWriter::finish`] after validating it.
///
/// Dropping the writer without finishing removes the temporary directory.
#[derive(Debug)]
pub struct BundleWriter {
    final_dir: PathBuf,
    /// `None` once finished, so `Drop` knows there is nothing to clean up.
    temp_dir: Option<PathBuf>,
    meta: BundleMeta,
    overwrite: bool,
    /// Indexed `[cam_index * frame_count + frame]`.
    frames_written: Vec<bool>,
    tracks_written: bool,
    particles_written: bool,
}

impl BundleWriter {
    /// Starts a new bundle at `final_dir`, which must not exist yet.
    pub fn create(final_dir: &Path, meta: BundleMeta) -> Result<Self> {
        Self::start(final_dir, meta, false)
    }

    /// Like [`BundleWriter::create`], but an existing `final_dir` is replaced in
    /// `finish`, and only once the new bundle is complete and valid.
    pub fn create_overwrite(final_dir: &Path, meta: BundleMeta) -> Result<Self> {
        Self::start(final_dir, meta, true)
    }

    fn start(final_dir: &Path, meta: BundleMeta, overwrite: bool) -> Result<Self> {
        meta.validate(&final_dir.join(BUNDLE_JSON))?;
        if !overwrite && final_dir.exists() {
            return Err(refuse_overwrite(final_dir));
        }
        if let Some(parent) = final_dir.parent().filter(|p| !p.as_os_str().is_empty()) {
            fs::create_dir_all(parent)
                .map_err(|e| BundleError::io(parent, "creating directory", &e))?;
        }
        // Earlier runs killed while writing this bundle left their copies.
        if let (Some(parent), Some(name)) = (final_dir.parent(), final_dir.file_name()) {
            let parent = if parent.as_os_str().is_empty() {
                Path::new(".")
            } else {
                parent
            };
            remove_abandoned_temporaries(parent, &format!("{}.tmp-", name.to_string_lossy()))?;
        }
        let temp_dir = unique_sibling(final_dir, "tmp");
        // The name embeds our pid, so an existing one is a leftover of a dead process.
        if temp_dir.exists() {
            fs::remove_dir_all(&temp_dir)
                .map_err(|e| BundleError::io(&temp_dir, "removing stale directory", &e))?;
        }
        let frame_slots = meta.cameras.len() * meta.frame_count;
        let writer = BundleWriter {
            final_dir: final_dir.to_path_buf(),
            temp_dir: Some(temp_dir.clone()),
            meta,
            overwrite,
            frames_written: vec![false; frame_slots],
            tracks_written: false,
            particles_written: false,
        };
        // From here on, `Drop` removes the temporary directory on any error.
        let mut dirs = vec![temp_dir.join(TRACKS_DIR), temp_dir.join(PARTICLES_DIR)];
        for camera in &writer.meta.cameras {
            for kind in ImageKind::ALL {
                dirs.push(
                    temp_dir
                        .join(VIEWS_DIR)
                        .join(&camera.name)
                        .join(kind.dir_name()),
                );
            }
        }
        for dir in dirs {
            fs::create_dir_all(&dir)
                .map_err(|e| BundleError::io(&dir, "creating directory", &e))?;
        }
        Ok(writer)
    }

    pub fn meta(&self) -> &BundleMeta {
        &self.meta
    }

    /// The directory being written; it becomes the final directory in `finish`.
    pub fn temp_dir(&self) -> Option<&Path> {
        self.temp_dir.as_deref()
    }

    fn temp_root(&self) -> Result<&Path> {
        // Unreachable through the public API (finish consumes self), but no panic either.
        self.temp_dir.as_deref().ok_or_else(|| {
            BundleError::new(
                &self.final_dir,
                crate::error::IO_FIELD,
                "writer already finished",
            )
        })
    }

    /// Writes the four images of one camera and frame. `depth_m` is row-major
    /// `width * height` in metres; see [`depth_m_to_png_mm`] for the encoding.
    pub fn write_frame_images(
        &mut self,
        cam_index: usize,
        frame: usize,
        rgb: &RgbImage,
        depth_m: &[f32],
        mask_object: &GrayImage,
        mask_hand: &GrayImage,
    ) -> Result<()> {
        let root = self.temp_root()?.to_path_buf();
        let path_of = |kind| image_path(&root, &self.meta, cam_index, frame, kind);
        let rgb_path = path_of(ImageKind::Rgb)?;
        let camera = &self.meta.cameras[cam_index];
        let size = (camera.width, camera.height);
        for (kind, dims) in [
            (ImageKind::Rgb, rgb.dimensions()),
            (ImageKind::MaskObject, mask_object.dimensions()),
            (ImageKind::MaskHand, mask_hand.dimensions()),
        ] {
            if dims != size {
                return Err(BundleError::new(
                    path_of(kind)?,
                    "size",
                    format!(
                        "image is {}x{} but camera \"{}\" is {}x{}",
                        dims.0, dims.1, camera.name, size.0, size.1
                    ),
                ));
            }
        }
        let depth_path = path_of(ImageKind::Depth)?;
        if depth_m.len() != camera.pixel_count() {
            return Err(BundleError::new(
                &depth_path,
                "size",
                format!(
                    "depth buffer has {} values, camera is {}x{}",
                    depth_m.len(),
                    size.0,
                    size.1
                ),
            ));
        }
        let depth_mm: Vec<u16> = depth_m.iter().map(|&d| depth_m_to_png_mm(d)).collect();
        let depth_image = ImageBuffer::<Luma<u16>, Vec<u16>>::from_raw(size.0, size.1, depth_mm)
            .ok_or_else(|| {
                BundleError::new(
                    &depth_path,
                    "size",
                    "depth buffer does not match the camera size",
                )
            })?;

        save_png(&rgb_path, rgb)?;
        save_png(&depth_path, &depth_image)?;
        save_png(&path_of(ImageKind::MaskObject)?, mask_object)?;
        save_png(&path_of(ImageKind::MaskHand)?, mask_hand)?;
        self.frames_written[cam_index * self.meta.frame_count + frame] = true;
        Ok(())
    }

    pub fn write_tracks(&mut self, tracks: &Tracks) -> Result<()> {
        let root = self.temp_root()?;
        write_npy_file(&root.join(OBJECT_POINTS_FILE), &tracks.object_points)?;
        write_npy_file(
            &root.join(OBJECT_VISIBILITY_FILE),
            &tracks.object_visibility,
        )?;
        write_npy_file(
            &root.join(OBJECT_MOTION_VALID_FILE),
            &tracks.object_motion_valid,
        )?;
        write_npy_file(&root.join(HAND_POINTS_FILE), &tracks.hand_points)?;
        write_npy_file(&root.join(HAND_VISIBILITY_FILE), &tracks.hand_visibility)?;
        self.tracks_written = true;
        Ok(())
    }

    pub fn write_particles(&mut self, particles: &FirstFrameParticles) -> Result<()> {
        let root = self.temp_root()?;
        write_npy_file(&root.join(SURFACE_POINTS_FILE), &particles.surface_points)?;
        write_npy_file(&root.join(SURFACE_COLORS_FILE), &particles.surface_colors)?;
        write_npy_file(&root.join(INTERIOR_POINTS_FILE), &particles.interior_points)?;
        write_npy_file(&root.join(INTERIOR_COLORS_FILE), &particles.interior_colors)?;
        self.particles_written = true;
        Ok(())
    }

    /// Writes the object mesh (Wavefront OBJ text) at `meta.mesh`, or at
    /// `mesh/object.obj` (recorded in `meta.mesh`) when none was set.
    pub fn write_mesh_obj(&mut self, obj_text: &str) -> Result<()> {
        let relative = self
            .meta
            .mesh
            .get_or_insert_with(|| DEFAULT_MESH_FILE.to_owned())
            .clone();
        let path = self.temp_root()?.join(&relative);
        if let Some(parent) = path.parent() {
            fs::create_dir_all(parent)
                .map_err(|e| BundleError::io(parent, "creating directory", &e))?;
        }
        fs::write(&path, obj_text).map_err(|e| BundleError::io(&path, "writing", &e))
    }

    /// Writes `bundle.json`, validates the whole temporary bundle with
    /// [`Bundle::open`], then renames it to the final directory.
    pub fn finish(mut self) -> Result<Bundle> {
        let root = self.temp_root()?.to_path_buf();
        self.check_complete(&root)?;
        write_json_atomic(&root.join(BUNDLE_JSON), &self.meta)?;
        let mut bundle = Bundle::open(&root)?;
        self.move_into_place(&root)?;
        // The temporary directory no longer exists under its old name.
        self.temp_dir = None;
        bundle.root = self.final_dir.clone();
        Ok(bundle)
    }

    fn check_complete(&self, root: &Path) -> Result<()> {
        let never_written = |relative: &str, method: &str| {
            BundleError::new(
                root.join(relative),
                crate::error::IO_FIELD,
                format!("never written (call {method})"),
            )
        };
        if !self.tracks_written {
            return Err(never_written(OBJECT_POINTS_FILE, "write_tracks"));
        }
        if !self.particles_written {
            return Err(never_written(SURFACE_POINTS_FILE, "write_particles"));
        }
        if let Some(slot) = self.frames_written.iter().position(|written| !written) {
            let (cam_index, frame) = (slot / self.meta.frame_count, slot % self.meta.frame_count);
            let path = image_path(root, &self.meta, cam_index, frame, ImageKind::Rgb)?;
            return Err(BundleError::new(
                path,
                crate::error::IO_FIELD,
                format!(
                    "images of camera {cam_index} frame {frame} never written (call write_frame_images)"
                ),
            ));
        }
        Ok(())
    }

    fn move_into_place(&self, temp: &Path) -> Result<()> {
        let final_dir = &self.final_dir;
        // Checked again here: the directory may have appeared since `create`, and
        // rename(2) would silently replace an empty directory.
        if !final_dir.exists() {
            return fs::rename(temp, final_dir)
                .map_err(|e| BundleError::io(final_dir, "renaming bundle into place", &e));
        }
        if !self.overwrite {
            return Err(refuse_overwrite(final_dir));
        }
        // Two renames leave a short window without a final directory, but never a
        // half-written one; the old bundle is deleted only after the swap.
        let old = unique_sibling(final_dir, "old");
        fs::rename(final_dir, &old)
            .map_err(|e| BundleError::io(final_dir, "moving old bundle aside", &e))?;
        if let Err(e) = fs::rename(temp, final_dir) {
            let _ = fs::rename(&old, final_dir);
            return Err(BundleError::io(final_dir, "renaming bundle into place", &e));
        }
        // The new bundle is in place; failing to delete the old copy is not worth failing for.
        let _ = fs::remove_dir_all(&old);
        Ok(())
    }
}

impl Drop for BundleWriter {
    fn drop(&mut self) {
        if let Some(temp) = self.temp_dir.take() {
            // Best effort: an unfinished bundle must not linger next to real ones.
            let _ = fs::remove_dir_all(temp);
        }
    }
}

fn refuse_overwrite(final_dir: &Path) -> BundleError {
    BundleError::new(
        final_dir,
        crate::error::IO_FIELD,
        "already exists; refusing to overwrite it (`--overwrite` replaces it in dm-prep, `overwrite=True` in Python, `BundleWriter::create_overwrite` in Rust)",
    )
}

fn save_png<P>(path: &Path, image: &ImageBuffer<P, Vec<P::Subpixel>>) -> Result<()>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
{
    image
        .save_with_format(path, ImageFormat::Png)
        .map_err(|e| BundleError::new(path, "png", format!("encoding/writing failed: {e}")))
}
